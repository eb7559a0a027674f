"""The segment bank on the built-in demo scene (ground-truth segments, captions teacher, exact
depth), through the CLI: lifted scales must rank like the regions' true 3D extents, and the
median scale must grow from parts to objects to groups."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from scipy.stats import spearmanr

from n2f2.cli import main
from n2f2.data import load_scene
from n2f2.data.synthetic import generate_demo_scene
from n2f2.segments.bank import SegmentBank
from n2f2.segments.encoders import get_encoder
from n2f2.segments.segmenters import segment_layers


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    root = tmp_path_factory.mktemp("demo")
    scene_dir = root / "scene"
    generate_demo_scene(scene_dir, num_views=8, width=96, height=72, supersample=1, num_points=500,
                        show_progress=False)
    bank_dir = root / "bank"  # the paper's eigenvalue scales (the cpu preset's default is area)
    rc = main(["segments", str(scene_dir), "--segmenter", "ground-truth", "--encoder", "captions",
               "--depth-source", "gt", "--scale-measure", "eigenvalue", "--out", str(bank_dir), "--quiet"])
    assert rc == 0
    return scene_dir, bank_dir


def _segments(bank: SegmentBank):
    scales, region, level = [], [], []
    for i in range(bank.num_images):
        rec = bank.record(i)
        src = np.asarray(bank.optional(i, "source_ids"))
        lay = segment_layers(np.asarray(rec.layers), rec.num_segments)
        scales.append(rec.scales[rec.valid])
        region.append(src[rec.valid])
        level.append(lay[rec.valid])
    return map(np.concatenate, (scales, region, level))


def test_lifted_scales_rank_like_true_extents(demo):
    scene_dir, bank_dir = demo
    bank = SegmentBank.open(bank_dir)
    regions = {r["id"]: r for r in json.loads((scene_dir / "regions.json").read_text())["regions"]}
    scales, region, level = _segments(bank)
    assert len(scales) > 100
    extent = np.array([regions[int(r)]["extent"] for r in region])
    assert spearmanr(scales, extent)[0] >= 0.9
    medians = [np.median(scales[level == lv]) for lv in range(3)]  # part, object, group
    assert medians[0] < medians[1] < medians[2]
    # bank.json reports the same check for users (computed independently above).
    check = json.loads((bank_dir / "bank.json").read_text())["ground_truth_check"]
    assert check["spearman_scale_vs_true_extent"] == pytest.approx(spearmanr(scales, extent)[0])
    assert list(check["median_scale_by_level"].values()) == pytest.approx(medians)
    assert list(check["median_scale_by_level"]) == ["part", "object", "group"]
    # GT layers are the part / object / group levels of regions.json
    assert all(regions[int(r)]["level"] == lv for r, lv in zip(region, level))


def test_bank_contract_for_training_and_queries(demo):
    scene_dir, bank_dir = demo
    bank = SegmentBank.open(bank_dir)
    scene = load_scene(scene_dir)
    bank.validate_against(scene)
    assert (bank.num_images, bank.height, bank.width, bank.embed_dim) == (8, 72, 96, 384)
    spec = bank.encoder_spec
    assert spec["name"] == "captions" and "stand-in for CLIP" in spec["description"]
    meta = json.loads((bank_dir / "bank.json").read_text())
    assert meta["counts"]["dropped_degenerate"] >= 0 and meta["quantile"]["knots"]
    # stored embeddings are the stored captions through the text encoder named in bank.json
    enc = get_encoder(spec)
    caps = json.loads((bank_dir / scene.image_names[0] / "captions.json").read_text())
    rec = bank.record(0)
    np.testing.assert_allclose(rec.embeddings.astype(np.float32), enc.encode_text(caps).numpy(), atol=2e-3)
    # layers: 3 levels; each region's pixels are where the ground truth says
    gt = scene.ground_truth.region_ids(0)
    src = np.asarray(bank.optional(0, "source_ids"))
    masks = rec.masks()
    layer_of = segment_layers(np.asarray(rec.layers), rec.num_segments)
    for k in range(rec.num_segments):
        assert np.array_equal(masks[k], gt[layer_of[k]] == src[k]), k
    q = rec.quantized[rec.valid]
    assert np.all((q >= 0) & (q < 1))


def test_downscaled_bank_and_rerun(demo, tmp_path):
    scene_dir, bank_dir = demo
    # a rerun of a finished bank skips every image and keeps it readable
    before = (bank_dir / "frame_00001" / "layers.npy").stat().st_mtime_ns
    assert main(["segments", str(scene_dir), "--segmenter", "ground-truth", "--encoder", "captions",
                 "--depth-source", "gt", "--scale-measure", "eigenvalue", "--out", str(bank_dir), "--resume",
                 "--quiet"]) == 0
    assert (bank_dir / "frame_00001" / "layers.npy").stat().st_mtime_ns == before
    out = tmp_path / "half"
    assert main(["segments", str(scene_dir), "--segmenter", "ground-truth", "--encoder", "captions",
                 "--depth-source", "gt", "--downscale", "2", "--out", str(out), "--quiet"]) == 0
    half = SegmentBank.open(out)
    assert (half.height, half.width) == (36, 48)
    half.validate_against(load_scene(scene_dir, downscale=2))
    with pytest.raises(Exception, match="downscale"):
        half.validate_against(load_scene(scene_dir))


def _parent_smaller_than_child(bank: SegmentBank, regions: dict) -> tuple[int, int]:
    """(pairs where a region's scale is below its own child's in the same view, all pairs)."""
    inverted = pairs = 0
    for i in range(bank.num_images):
        rec = bank.record(i)
        scale = {int(r): s for r, s, ok in zip(bank.optional(i, "source_ids"), rec.scales, rec.valid) if ok}
        for r, s in scale.items():
            parent = regions[r]["parent"]
            if parent in scale:
                pairs += 1
                inverted += scale[parent] < s
    return inverted, pairs


def test_extent_scale_measure(demo, tmp_path, capsys):
    scene_dir, bank_dir = demo
    out = tmp_path / "extent"
    args = ["segments", str(scene_dir), "--segmenter", "ground-truth", "--encoder", "captions",
            "--depth-source", "gt", "--scale-measure", "extent", "--quiet"]
    assert main([*args, "--out", str(out)]) == 0
    lifting = json.loads((out / "bank.json").read_text())["lifting"]
    assert lifting["scale_measure"] == "extent" and "oriented box" in lifting["scale"]
    regions = {r["id"]: r for r in json.loads((scene_dir / "regions.json").read_text())["regions"]}
    eig_inverted, pairs = _parent_smaller_than_child(SegmentBank.open(bank_dir), regions)
    ext_inverted, ext_pairs = _parent_smaller_than_child(SegmentBank.open(out), regions)
    assert pairs == ext_pairs > 50
    assert ext_inverted < eig_inverted, (ext_inverted, eig_inverted)
    # The eigenvalue bank's folder does not take extent records.
    capsys.readouterr()
    assert main([*args, "--out", str(bank_dir), "--resume"]) == 2
    assert "lifting settings" in capsys.readouterr().err


def test_cli_errors(demo, tmp_path, capsys):
    scene_dir, _ = demo
    rc = main(["segments", str(scene_dir), "--segmenter", "ground-truth", "--encoder", "captions",
               "--out", str(tmp_path / "b")])
    assert rc == 2 and "--gaussians" in capsys.readouterr().err
    rc = main(["segments", str(scene_dir), "--gaussians", str(tmp_path / "nope.ply"), "--segmenter",
               "ground-truth", "--encoder", "captions", "--out", str(tmp_path / "b")])
    assert rc == 2 and "nope.ply" in capsys.readouterr().err
    rc = main(["segments-from-langsplat", str(scene_dir), "--depth-source", "gt", "--out", str(tmp_path / "c")])
    assert rc == 2 and "language_features" in capsys.readouterr().err


def test_render_depth_provider_on_a_sheet_of_gaussians():
    """A dense sheet of small opaque Gaussians at z = 2 in front of the camera: the provider's
    depth is 2 where the sheet covers the image and marked invalid elsewhere."""
    from n2f2.cameras import Camera
    from n2f2.gaussians import Gaussians
    from n2f2.segments.lifting import render_depth_provider

    xs, ys = np.meshgrid(np.linspace(-0.5, 0.5, 26), np.linspace(-0.4, 0.4, 21))
    means = torch.tensor(np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, 2.0)], 1), dtype=torch.float32)
    n = means.shape[0]
    g = Gaussians(means, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.full((n, 3), np.log(0.03)),
                  torch.full((n,), 5.0), torch.zeros(n, 1, 3))
    cam = Camera(20.0, 20.0, 16.0, 12.0, 32, 24)  # identity pose: looking down +z
    depth, valid = render_depth_provider(g, [cam])(0)
    assert depth.shape == (24, 32) and valid.shape == (24, 32)
    # the sheet spans x in [-0.5, 0.5] at z = 2 -> u in 16 +- 5 px; y in [-0.4, 0.4] -> v in 12 +- 4 px
    assert valid[9:15, 12:20].all() and not valid[:, :5].any()
    np.testing.assert_allclose(depth[valid], 2.0, atol=0.02)
