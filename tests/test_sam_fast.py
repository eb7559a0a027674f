"""SAM's fast mask decoder against ``SamModel``'s own forward, on a tiny random SAM whose weights
are scaled up so that attention is peaked and mask logits are O(1) (with the default
initialisation every attention is nearly uniform and every logit nearly zero, which would hide
a wrong softmax axis or a dropped bias).

Tolerances: IoU predictions and low-res logits within 1e-4 + 1e-5 x |value| (float32 sums in a
different order differ by up to ~4e-5 here, on logits up to ~16); the segmenter's final masks
equal, or IoU >= 0.99 per mask where a logit within rounding of the threshold flips a pixel."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from n2f2.segments.sam import (
    FastSamDecoder,
    SamSegmenter,
    SamSettings,
    contiguous_rel_pos,
    fast_decode,
    reference_decode,
)

ATOL, RTOL = 1e-4, 1e-5


@pytest.fixture(scope="module")
def sam_model():
    return tiny_sam()


def tiny_sam():
    """A tiny random SAM (image 128 px -> 8 x 8 embedding, decoder width 32, 4 heads) with
    weights of realistic scale."""
    from transformers import SamConfig, SamModel
    from transformers.models.sam.configuration_sam import SamMaskDecoderConfig, SamPromptEncoderConfig, SamVisionConfig

    torch.manual_seed(0)
    vision = SamVisionConfig(
        image_size=128,
        patch_size=16,
        hidden_size=32,
        output_channels=32,
        num_hidden_layers=2,
        num_attention_heads=2,
        mlp_dim=64,
        global_attn_indexes=[1],
        window_size=4,
        num_pos_feats=16,
    )
    prompt = SamPromptEncoderConfig(hidden_size=32, image_size=128, patch_size=16, mask_input_channels=4)
    decoder = SamMaskDecoderConfig(
        hidden_size=32, num_hidden_layers=2, num_attention_heads=4, mlp_dim=64, iou_head_hidden_dim=32
    )
    model = SamModel(
        SamConfig(
            vision_config=vision.to_dict(),
            prompt_encoder_config=prompt.to_dict(),
            mask_decoder_config=decoder.to_dict(),
        )
    ).eval()
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if "positional_embedding" in name:  # random Fourier features: keep their scale
                continue
            if "layer_norm" in name and name.endswith("weight"):
                p.copy_(1 + 0.3 * torch.randn(p.shape, generator=gen))
            elif p.dim() >= 2 and "embed" not in name and "token" not in name:
                fan_in = p.shape[0] if "upscale_conv" in name else p[0].numel()
                p.copy_(1.5 * torch.randn(p.shape, generator=gen) / fan_in**0.5)
            else:  # biases, embeddings, tokens
                p.copy_(0.5 * torch.randn(p.shape, generator=gen))
    return model


def _image(kind: str) -> np.ndarray:
    """Synthetic photos with shapes: 'rects' (96 x 128) and 'discs' (112 x 80)."""
    if kind == "rects":
        img = np.full((96, 128, 3), 0.2, np.float32)
        img[10:50, 15:70] = (0.9, 0.1, 0.1)
        img[40:90, 60:120] = (0.1, 0.8, 0.3)
        img[60:80, 5:40] = (0.1, 0.2, 0.9)
        return img
    yy, xx = np.mgrid[:112, :80]
    img = np.stack([0.5 + 0.3 * np.sin(xx / 7.0), 0.4 + 0.0 * yy, 0.3 + 0.2 * np.cos(yy / 9.0)], -1)
    for cy, cx, r, col in [(30, 25, 18, (1.0, 0.9, 0.1)), (75, 50, 25, (0.1, 0.1, 0.6)), (95, 15, 10, (0.9, 0.9, 0.9))]:
        img[(yy - cy) ** 2 + (xx - cx) ** 2 < r * r] = col
    return img.astype(np.float32)


def _embeddings_and_points(model, kind: str, n_side: int = 6):
    seg = SamSegmenter(model, SamSettings(points_per_side=n_side))
    img = _image(kind)
    H, W = img.shape[:2]
    pixels, (h, w) = seg.preprocess(img)
    with torch.inference_mode():
        emb = model.get_image_embeddings(pixels)
    points = torch.as_tensor(seg.point_grid(H, W), dtype=torch.float32) * torch.tensor([w / W, h / H])
    return emb, points


@pytest.mark.parametrize("kind", ["rects", "discs"])
def test_fast_decoder_equals_reference(sam_model, kind):
    emb, points = _embeddings_and_points(sam_model, kind)
    with torch.inference_mode():
        want_iou, want = reference_decode(sam_model, emb, points)
        got_iou, got = fast_decode(sam_model, emb, points)
    assert got_iou.shape == want_iou.shape == (36, 3) and got.shape == want.shape == (36, 3, 32, 32)
    assert want.abs().amax() > 1.0 and want_iou.std() > 0.1  # the test model is not degenerate
    torch.testing.assert_close(got_iou, want_iou, atol=ATOL, rtol=RTOL)
    torch.testing.assert_close(got, want, atol=ATOL, rtol=RTOL)


def test_fast_decoder_chunks_and_iou_selection(sam_model):
    """Prompt groups that do not divide the batch (10 prompts, 3 at a time; mask bands of 3 of
    the 8 token rows) give the same outputs, and ``min_iou`` returns exactly the masks above
    it, in order (some, none, all)."""
    emb, points = _embeddings_and_points(sam_model, "discs")
    points = points[7:17]
    with torch.inference_mode():
        want_iou, want = reference_decode(sam_model, emb, points)
        decoder = FastSamDecoder(sam_model, emb, chunk=3, tile_tokens=24)
        got_iou, got = decoder(points)
        threshold = float(want_iou.median())
        sel_iou, sel, index = decoder.decode(points, min_iou=threshold)
        none_iou, none, none_index = decoder.decode(points, min_iou=1e9)
        _, every, every_index = decoder.decode(points, min_iou=-1e9)
    torch.testing.assert_close(got_iou, want_iou, atol=ATOL, rtol=RTOL)
    torch.testing.assert_close(got, want, atol=ATOL, rtol=RTOL)
    expected = torch.nonzero(sel_iou.reshape(-1) > threshold).flatten()
    assert 0 < len(index) < 30 and index.tolist() == expected.tolist()
    torch.testing.assert_close(sel, want.reshape(-1, 32, 32)[index], atol=ATOL, rtol=RTOL)
    torch.testing.assert_close(none_iou, want_iou, atol=ATOL, rtol=RTOL)
    assert none.shape == (0, 32, 32) and none_index.numel() == 0
    assert every_index.tolist() == list(range(30))
    torch.testing.assert_close(every, want.reshape(-1, 32, 32), atol=ATOL, rtol=RTOL)


def _masks_by_score(segs):
    order = np.argsort(-segs.scores, kind="stable")
    return segs.masks(order.tolist()), segs.scores[order]


@pytest.mark.parametrize("kind", ["rects", "discs"])
def test_segmenter_fast_path_gives_the_reference_masks(sam_model, kind):
    """The whole segmenter (IoU filter, stability, NMS, small regions, LangSplat's NMS) on the
    fast decoder keeps the same masks as on ``SamModel``'s forward; 49 prompts, 10 a batch."""
    # Thresholds this random model passes partly (its masks are alike: NMS only drops near-copies).
    st = SamSettings(
        points_per_side=7,
        points_per_batch=10,
        pred_iou_thresh=-1.0,
        stability_score_thresh=0.5,
        stability_score_offset=0.3,
        min_mask_region_area=10,
        box_nms_thresh=0.97,
        nms_iou_thr=0.97,
        nms_score_thr=-1e9,
        nms_inner_thr=0.0,
    )
    img = _image(kind)
    fast = SamSegmenter(sam_model, st)
    ref = SamSegmenter(sam_model, replace(st, fast_decoder=False))
    got, want = fast(img), ref(img)
    assert fast.last_counts["iou_kept"] < fast.last_counts["candidates"]  # the IoU filter selects
    assert fast.last_counts == ref.last_counts
    assert want.num_segments >= 5 and got.num_segments == want.num_segments
    got_masks, got_scores = _masks_by_score(got)
    want_masks, want_scores = _masks_by_score(want)
    np.testing.assert_allclose(got_scores, want_scores, atol=ATOL, rtol=RTOL)
    for g, w in zip(got_masks, want_masks):
        assert (g & w).sum() / max(1, (g | w).sum()) >= 0.99


def test_fast_decoder_setting_is_not_part_of_the_spec(sam_model):
    """A bank's segmenter spec names what the masks are, not how they were computed."""
    a = SamSegmenter(sam_model, SamSettings()).spec
    b = SamSegmenter(sam_model, SamSettings(fast_decoder=False)).spec
    assert a == b and "fast_decoder" not in a


def test_fast_decoder_runs_under_autocast(sam_model):
    """Mixed precision (bfloat16 autocast on CPU, like float16 on CUDA): the fast path runs
    and stays close to the reference under the same autocast."""
    emb, points = _embeddings_and_points(sam_model, "rects", n_side=3)
    with torch.inference_mode(), torch.autocast("cpu", dtype=torch.bfloat16):
        want_iou, want = reference_decode(sam_model, emb, points)
        got_iou, got = fast_decode(sam_model, emb, points)
    assert torch.isfinite(got.float()).all()
    scale = want.float().abs().amax()
    assert (got.float() - want.float()).abs().amax() < 0.1 * scale
    assert (got_iou.float() - want_iou.float()).abs().amax() < 0.1 * want_iou.float().abs().amax()


def test_contiguous_rel_pos_gives_the_same_embeddings(sam_model):
    """The image encoder with its relative-position bias built contiguously: the same
    embeddings bit for bit, both attention layers (windowed and global) switched, and the
    model as it was afterwards."""
    seg = SamSegmenter(sam_model, SamSettings())
    pixels, _ = seg.preprocess(_image("discs"))
    attention = [m for m in sam_model.vision_encoder.modules() if hasattr(m, "get_decomposed_rel_pos")]
    with torch.inference_mode():
        want = sam_model.get_image_embeddings(pixels)
        with contiguous_rel_pos(sam_model) as layers:
            assert all("get_decomposed_rel_pos" in vars(m) for m in attention)
            got = sam_model.get_image_embeddings(pixels)
    assert layers == len(attention) == 2
    assert not any("get_decomposed_rel_pos" in vars(m) for m in attention)
    assert torch.equal(got, want)
