"""The ``sam2`` segmenter (SAM 2.1 through ``transformers.Sam2Model``) on a tiny random SAM 2
whose masks pass the paper's filters, against a plainly written automatic mask generator; and
the segmenter registry (``SEGMENTERS``, ``get_segmenter``)."""

from __future__ import annotations

import copy
import math
import subprocess
import sys
from dataclasses import asdict, replace

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from n2f2.errors import MissingModelError
from n2f2.segments.sam import SAM_PIXEL_MEAN, SAM_PIXEL_STD, SamSettings
from n2f2.segments.sam2 import DEFAULT_SAM2_MODEL, FastSam2Decoder, Sam2Segmenter, Sam2Settings
from n2f2.segments.segmenters import (
    SEGMENTER_NAMES,
    SEGMENTERS,
    ClassicalSegmenter,
    SegmentSet,
    get_segmenter,
    mask_nms,
    remove_small_regions,
)

# The paper's filters (IoU 0.7, stability 0.85, LangSplat's NMS), a small grid in uneven
# batches (36 points, 8 a batch), a minimum area that suits 40-pixel images, and no early NMS
# (the reference runs one NMS over all masks).
SETTINGS = Sam2Settings(points_per_side=6, points_per_batch=8, min_mask_region_area=10, max_pending_masks=10_000)


def tiny_sam2_config(video: bool = False):
    """SAM 2 at test size: 128 x 128 input, Hiera with 4 stages (8 to 64 wide), 32-d neck,
    prompt encoder and decoder; 32 x 32 mask logits. ``video``: as ``Sam2VideoConfig`` (the
    type of the released SAM 2.1 folders)."""
    from transformers import Sam2Config, Sam2VideoConfig
    from transformers.models.sam2.configuration_sam2 import Sam2HieraDetConfig, Sam2VisionConfig

    trunk = Sam2HieraDetConfig(hidden_size=8, num_attention_heads=1, image_size=[128, 128],
                               embed_dim_per_stage=[8, 16, 32, 64], num_attention_heads_per_stage=[1, 1, 2, 2],
                               blocks_per_stage=[1, 1, 2, 1], global_attention_blocks=[3],
                               window_size_per_stage=[8, 4, 4, 2], window_positional_embedding_background_size=[4, 4])
    vision = Sam2VisionConfig(backbone_config=trunk.to_dict(), backbone_channel_list=[64, 32, 16, 8],
                              backbone_feature_sizes=[[32, 32], [16, 16], [8, 8]], fpn_hidden_size=32)
    prompt = dict(hidden_size=32, image_size=128, patch_size=16, mask_input_channels=4)
    decoder = dict(hidden_size=32, mlp_dim=64, num_attention_heads=2, iou_head_hidden_dim=32)
    cls = Sam2VideoConfig if video else Sam2Config
    return cls(vision_config=vision.to_dict(), prompt_encoder_config=prompt, mask_decoder_config=decoder)


@pytest.fixture(scope="module")
def tiny_sam2():
    """A random tiny ``Sam2Model`` rescaled so that the paper's filters bite: predicted IoUs
    spread around 0.7 (40 % pass) and mask logits span tens of units (about half of those
    masks are stable)."""
    from transformers import Sam2Model

    torch.manual_seed(0)
    model = Sam2Model(tiny_sam2_config()).eval()
    dec = model.mask_decoder
    raw = []
    hook = dec.iou_prediction_head.proj_out.register_forward_hook(lambda m, i, o: raw.append(o))
    with torch.no_grad():
        x = torch.randn(1, 3, 128, 128, generator=torch.Generator().manual_seed(1))
        points = torch.rand(1, 16, 1, 2, generator=torch.Generator().manual_seed(2)) * 128
        out = model(pixel_values=x, input_points=points, multimask_output=True)
        hook.remove()
        z = raw[0][..., 1:]  # IoU logits of the three multimask outputs
        head, g = dec.iou_prediction_head.proj_out, 2.0 / float(z.std())
        head.weight.mul_(g)
        head.bias.mul_(g).add_(math.log(0.7 / 0.3) - g * float(z.mean()))  # IoU logits ~ N(logit(0.7), 2)
        gain = 24.0 / float(out.pred_masks.std())
        for mlp in dec.output_hypernetworks_mlps:
            mlp.proj_out.weight.mul_(gain)
            mlp.proj_out.bias.mul_(gain)
    return model


def photo(which: str, height: int, width: int) -> np.ndarray:
    """A real photo from scikit-image, resized to [height, width, 3] float32 in [0, 1]."""
    from skimage import data as skdata
    from skimage.transform import resize

    return resize(getattr(skdata, which)(), (height, width), anti_aliasing=True).astype(np.float32)


# ----------------------------------------------------------------------------- plain reference
def reference_segments(model, image: np.ndarray, st: SamSettings) -> tuple[SegmentSet, dict]:
    """SAM 2's automatic mask generation written out plainly: the model's full forward (image
    encoder included) per batch of prompts, then per mask the IoU filter, upsampling to the
    image, stability, greedy NMS on mask IoU; then n2f2's shared steps (small regions,
    LangSplat's mask NMS, packing). Returns the segments and the mask counts after each step."""
    H, W = image.shape[:2]
    T = model.config.prompt_encoder_config.image_size
    x = torch.from_numpy(image).permute(2, 0, 1)[None]
    x = F.interpolate(x, size=(T, T), mode="bilinear", align_corners=False, antialias=True)  # no aspect, no pad
    x = (x - torch.tensor(SAM_PIXEL_MEAN).view(1, 3, 1, 1)) / torch.tensor(SAM_PIXEL_STD).view(1, 3, 1, 1)
    n = st.points_per_side
    # Grid cell centres, row by row: image (x, y) = ((i + 0.5) W / n, (j + 0.5) H / n), in the
    # model's frame (x T / W, y T / H).
    points = [((i + 0.5) / n * T, (j + 0.5) / n * T) for j in range(n) for i in range(n)]
    masks, ious, stabs = [], [], []
    counts = {"candidates": 0, "iou_kept": 0}
    with torch.no_grad():
        for start in range(0, len(points), st.points_per_batch):
            batch = torch.tensor(points[start : start + st.points_per_batch])
            out = model(pixel_values=x, input_points=batch[None, :, None, :], multimask_output=True)
            for p in range(len(batch)):
                for k in range(3):
                    iou = float(out.iou_scores[0, p, k])
                    counts["candidates"] += 1
                    if not iou > st.pred_iou_thresh:
                        continue
                    counts["iou_kept"] += 1
                    logits = F.interpolate(out.pred_masks[0, p, k][None, None], size=(H, W), mode="bilinear",
                                           align_corners=False)[0, 0]
                    hi = int((logits > st.mask_threshold + st.stability_score_offset).sum())
                    lo = int((logits > st.mask_threshold - st.stability_score_offset).sum())
                    stability = hi / max(lo, 1)
                    mask = (logits > st.mask_threshold).numpy()
                    if stability >= st.stability_score_thresh and mask.any():
                        masks.append(mask)
                        ious.append(iou)
                        stabs.append(stability)
    counts["stable"] = len(masks)
    kept = []
    for i in sorted(range(len(masks)), key=lambda i: -ious[i]):
        if all((masks[i] & masks[j]).sum() / (masks[i] | masks[j]).sum() <= st.box_nms_thresh for j in kept):
            kept.append(i)
    counts["after_nms"] = len(kept)
    cleaned = [remove_small_regions(masks[i], st.min_mask_region_area) for i in kept]
    big = [c.sum() >= st.min_mask_region_area for c in cleaned]
    final = np.array([c for c, b in zip(cleaned, big) if b])
    score = torch.tensor([ious[i] * stabs[i] for i, b in zip(kept, big) if b], dtype=torch.float32)
    order = mask_nms(torch.from_numpy(final), score, st.nms_iou_thr, st.nms_score_thr, st.nms_inner_thr)
    counts["final"] = len(order)
    return SegmentSet.from_masks(final[order.numpy()], score[order].numpy()), counts


@pytest.mark.parametrize("fast_decoder", [True, False])
@pytest.mark.parametrize("which, height, width", [("astronaut", 40, 56), ("coffee", 170, 110)])
def test_sam2_masks_equal_the_plain_reference(tiny_sam2, which, height, width, fast_decoder):
    """Every segment of the segmenter equals the reference's (same order, IoU >= 0.99, same
    score, the same mask counts after each step), on a small landscape photo and a portrait one
    larger than the model's input (stretched differently, shrunk in one direction); with the
    fast decoder and with ``Sam2Model``'s forward from the cached image features."""
    image = photo(which, height, width)
    seg = Sam2Segmenter(tiny_sam2, replace(SETTINGS, fast_decoder=fast_decoder), model_id="tiny-random-sam2")
    got = seg(image)
    want, counts = reference_segments(tiny_sam2, image, SETTINGS)
    assert seg.last_counts == counts and counts["candidates"] == 3 * 36
    # every step drops some masks
    assert counts["candidates"] > counts["iou_kept"] > counts["stable"] > counts["after_nms"] > counts["final"] >= 2
    assert got.num_segments == want.num_segments
    a, b = got.masks(), want.masks()
    iou = (a & b).sum(axis=(1, 2)) / (a | b).sum(axis=(1, 2))
    assert iou.min() >= 0.99, iou
    np.testing.assert_allclose(got.scores, want.scores, rtol=0, atol=1e-5)
    assert got.layers.shape[1:] == (height, width)
    assert seg.spec["name"] == "sam2" and seg.spec["model_id"] == "tiny-random-sam2"


@pytest.fixture(scope="module")
def tiny_sam2_with_biases(tiny_sam2):
    """``tiny_sam2`` with random biases in every linear layer of the mask decoder's transformer
    (``transformers`` initialises them to zero; trained ones are not), which the fast decoder
    moves around, and 10x weights there, so that attention is far from uniform and every bias
    but the key projections' (which cancel in the softmax) changes the masks measurably."""
    model = copy.deepcopy(tiny_sam2)
    with torch.no_grad():
        for module in model.mask_decoder.transformer.modules():
            if isinstance(module, torch.nn.Linear):
                module.weight.mul_(10.0)
                module.bias.normal_(0.0, 0.5, generator=torch.Generator().manual_seed(module.bias.numel()))
    return model


@pytest.mark.parametrize("biases", [False, True])
@pytest.mark.parametrize("chunk, mask_chunk", [(4, 2), (3, 5), (1, 1)])
def test_fast_decoder_equals_the_models_forward(tiny_sam2, tiny_sam2_with_biases, chunk, mask_chunk, biases):
    """IoU predictions and low-res logits of :class:`FastSam2Decoder` equal ``Sam2Model``'s
    forward up to float rounding, in any grouping of prompts, with zero or random biases; with
    an IoU threshold it returns exactly the masks above it."""
    model = tiny_sam2_with_biases if biases else tiny_sam2
    seg = Sam2Segmenter(model)
    with torch.no_grad():
        x, _ = seg.preprocess(photo("astronaut", 40, 56))
        embeddings = model.get_image_embeddings(x)
        points = torch.rand(11, 2, generator=torch.Generator().manual_seed(3)) * 128
        want_iou, want = seg.reference_decode(embeddings, points)  # [11, 3], [11, 3, 32, 32]
        want = want.flatten(0, 1)
        fast = FastSam2Decoder(model, embeddings, chunk=chunk, mask_chunk=mask_chunk)
        iou, low, index = fast.decode(points)
        torch.testing.assert_close(iou, want_iou, atol=1e-5, rtol=0)
        assert index.tolist() == list(range(33))
        torch.testing.assert_close(low, want, atol=1e-4 * float(want.abs().max()), rtol=0)
        iou, low, index = fast.decode(points, min_iou=0.7)
        above = torch.nonzero(want_iou.flatten() > 0.7).flatten()
        assert 0 < len(above) < 33 and index.tolist() == above.tolist()
        torch.testing.assert_close(low, want[above], atol=1e-4 * float(want.abs().max()), rtol=0)
        iou, low, index = fast.decode(points, min_iou=2.0)
        assert low.shape == (0, 32, 32) and index.numel() == 0 and iou.shape == (11, 3)


def test_fast_decoder_setting_picks_the_decoder(tiny_sam2, monkeypatch):
    """``fast_decoder`` (default True) decodes with :class:`FastSam2Decoder`; False with
    ``Sam2Model``'s forward (:meth:`Sam2Segmenter.reference_decode`) only."""
    import n2f2.segments.sam2 as sam2

    used = []

    class Spy(FastSam2Decoder):
        def decode(self, points, min_iou=None):
            used.append("fast")
            return super().decode(points, min_iou)

    plain = Sam2Segmenter.reference_decode

    def forward(self, embeddings, points):
        used.append("forward")
        return plain(self, embeddings, points)

    monkeypatch.setattr(sam2, "FastSam2Decoder", Spy)
    monkeypatch.setattr(Sam2Segmenter, "reference_decode", forward)
    image = photo("astronaut", 40, 56)
    Sam2Segmenter(tiny_sam2, replace(SETTINGS, points_per_side=2))(image)
    assert used == ["fast"]
    used.clear()
    Sam2Segmenter(tiny_sam2, replace(SETTINGS, points_per_side=2, fast_decoder=False))(image)
    assert used == ["forward"]


def test_sam2_input_frame_and_upsampling(tiny_sam2):
    """SAM 2's frame: the image stretched to the square input (no padding), and 32 x 32 logits
    upsampled straight to the image; a logit block covering the top-left quarter of the frame
    covers the top-left quarter of the image, whatever its aspect."""
    seg = Sam2Segmenter(tiny_sam2, SETTINGS)
    x, frame = seg.preprocess(np.ones((30, 70, 3), np.float32))
    assert x.shape == (1, 3, 128, 128) and frame == (128, 128)
    assert torch.allclose(x[0, :, -1, -1], (1 - torch.tensor(SAM_PIXEL_MEAN)) / torch.tensor(SAM_PIXEL_STD))
    low = torch.full((1, 32, 32), -10.0)
    low[0, :16, :16] = 10.0
    mask = seg.postprocess_masks(low, frame, (30, 70))[0] > 0
    assert mask.shape == (30, 70) and mask[:15, :35].all() and not mask[15:].any() and not mask[:, 35:].any()


# ----------------------------------------------------------------------------- loading and registry
def test_get_segmenter_sam2_loads_a_saved_folder(tmp_path, tiny_sam2):
    """``get_segmenter("sam2", model_id=DIR)`` builds the segmenter from a ``save_pretrained``
    folder with the given settings, and a folder saved as ``Sam2VideoModel`` (the type of the
    released SAM 2.1 checkpoints) loads too, giving the same segments."""
    from transformers import Sam2VideoModel

    tiny_sam2.save_pretrained(tmp_path / "sam2")
    settings = asdict(SETTINGS)
    seg = get_segmenter("sam2", model_id=str(tmp_path / "sam2"), **settings)
    assert isinstance(seg, Sam2Segmenter) and seg.settings == SETTINGS
    assert seg.spec["model_id"] == str(tmp_path / "sam2") and seg.spec["points_per_side"] == 6
    image = photo("astronaut", 40, 56)
    want = Sam2Segmenter(tiny_sam2, SETTINGS)(image)
    got = seg(image)
    assert got.num_segments == want.num_segments > 0 and np.array_equal(got.layers, want.layers)

    video = Sam2VideoModel(tiny_sam2_config(video=True)).eval()
    missing = video.load_state_dict(tiny_sam2.state_dict(), strict=False).missing_keys
    assert missing and all(not k.startswith(("vision_encoder", "mask_decoder", "prompt_encoder")) for k in missing)
    video.save_pretrained(tmp_path / "sam2-video")
    from_video = get_segmenter("sam2", model_id=str(tmp_path / "sam2-video"), **settings)(image)
    assert np.array_equal(from_video.layers, want.layers)


def test_missing_sam2_model_gives_one_clear_message(monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    with pytest.raises(MissingModelError) as e:
        get_segmenter("sam2", model_id="n2f2-tests/no-such-sam2-model")
    msg = str(e.value)
    assert "SAM 2.1 model 'n2f2-tests/no-such-sam2-model'" in msg and "hf download" in msg and "--local-dir DIR" in msg
    assert "--sam-model" in msg and "--segmenter classical" in msg


def test_registry_names_defaults_and_unknown_name():
    from n2f2.segments import sam

    assert SEGMENTER_NAMES == tuple(SEGMENTERS) == ("sam", "sam2", "classical", "ground-truth")
    assert SEGMENTERS["sam"].default_model_id == sam.DEFAULT_SAM_MODEL
    assert SEGMENTERS["sam2"].default_model_id == DEFAULT_SAM2_MODEL == "facebook/sam2.1-hiera-tiny"
    assert SEGMENTERS["sam2"].settings_class() is Sam2Settings and SEGMENTERS["ground-truth"].needs_scene
    assert all(kind.description for kind in SEGMENTERS.values())
    with pytest.raises(ValueError) as e:
        get_segmenter("sam3")
    assert str(e.value) == "unknown segmenter 'sam3'; choose one of sam, sam2, classical, ground-truth"
    # The existing names behave as before.
    classical = get_segmenter("classical", scales=(50.0,), min_area=20)
    assert isinstance(classical, ClassicalSegmenter) and classical.settings.scales == (50.0,)
    with pytest.raises(ValueError, match="^the ground-truth segmenter needs the scene$"):
        get_segmenter("ground-truth")
    with pytest.raises(TypeError, match="no_such_setting"):
        get_segmenter("sam2", no_such_setting=1)
    with pytest.raises(TypeError, match="no_such_setting"):
        get_segmenter("sam", no_such_setting=1)


def test_segmenters_module_does_not_import_the_model_modules():
    """``segmenters`` registers ``sam`` and ``sam2`` without importing them (the CLI imports the
    registry for its choices)."""
    code = (
        "import sys, n2f2.segments.segmenters as s; "
        "print(sorted(m for m in sys.modules if m in ('n2f2.segments.sam', 'n2f2.segments.sam2', 'transformers')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_sam2_settings_are_sams(tiny_sam2):
    """Defaults are the paper's / LangSplat's, as for ``sam``; changed fields reach the spec;
    the decoder choice does not (it does not change the masks)."""
    seg = Sam2Segmenter(tiny_sam2)
    assert isinstance(seg.settings, Sam2Settings) and seg.settings.fast_decoder
    sam_spec = {k: v for k, v in asdict(SamSettings()).items() if k != "fast_decoder"}
    assert seg.spec == {"name": "sam2", "model_id": "", **sam_spec}
    assert Sam2Segmenter(tiny_sam2, replace(SamSettings(), points_per_side=8)).spec["points_per_side"] == 8
    assert Sam2Segmenter(tiny_sam2, Sam2Settings(fast_decoder=False)).spec == seg.spec
