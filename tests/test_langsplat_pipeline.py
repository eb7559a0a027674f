"""LangSplat-format features end to end: a demo segment bank exported as LangSplat
``language_features`` and imported again must give back the same segments and embeddings, and
``n2f2 run`` must work on a scene folder in nerfstudio format only (images, transforms.json,
its sparse_pc.ply) with those features, LangSplat labels and the MiniLM text encoder."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from n2f2.cli import main
from n2f2.data import load_scene
from n2f2.data.synthetic import generate_demo_scene
from n2f2.segments.bank import SegmentBank
from n2f2.segments.encoders import get_encoder
from n2f2.segments.langsplat import langsplat_maps, read_langsplat
from n2f2.segments.segmenters import segment_layers

# LangSplat level -> demo level exported into it (default, s, m, l).
EXPORTED_LEVELS = ("object", "part", "object", "group")


def _cli(*argv) -> None:
    rc = main([str(a) for a in argv])
    assert rc == 0, f"n2f2 {' '.join(map(str, argv))} exited {rc}"


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """Demo scene, its ground-truth bank (captions teacher, exact depth) and the bank exported
    as LangSplat features."""
    root = tmp_path_factory.mktemp("langsplat")
    scene = root / "scene"
    generate_demo_scene(scene, num_views=6, width=80, height=60, seed=0, labelled_views=[1, 4],
                        show_progress=False)
    bank = root / "bank"
    _cli("segments", scene, "--segmenter", "ground-truth", "--encoder", "captions", "--depth-source", "gt",
         "--out", bank, "--quiet")
    features = root / "language_features"
    _cli("segments-export-langsplat", bank, "--out", features, "--quiet")
    return root, scene, bank, features


def nerfstudio_langsplat_scene(scene: Path, features: Path, out: Path) -> Path:
    """A copy of the demo scene with only what a nerfstudio + LangSplat scene has: images/,
    transforms.json and the point cloud it names, language_features/, label/ (no COLMAP
    model, no ground-truth regions, depth or queries.json)."""
    out.mkdir(parents=True)
    shutil.copytree(scene / "images", out / "images")
    shutil.copytree(scene / "label", out / "label")
    shutil.copytree(features, out / "language_features")
    meta = json.loads((scene / "transforms.json").read_text())
    shutil.copy(scene / "transforms.json", out / "transforms.json")
    if meta.get("ply_file_path"):
        shutil.copy(scene / meta["ply_file_path"], out / meta["ply_file_path"])
    return out


def test_langsplat_maps_hand_example():
    # bank ids: layer 0 holds 3 and 1, layer 1 holds 0, layer 2 holds 2 and 4
    layers = np.array([[[3, 3, -1], [1, -1, -1]],
                       [[0, 0, 0], [-1, 0, -1]],
                       [[2, 4, 4], [2, 2, -1]]], np.int32)
    maps, rows = langsplat_maps(layers, (1, 0, 1, 2))
    # default <- layer 1 (rows 0), s <- layer 0 (ids 1, 3 -> rows 1, 2), m <- layer 1 (row 3),
    # l <- layer 2 (ids 2, 4 -> rows 4, 5)
    assert rows.tolist() == [0, 1, 3, 0, 2, 4]
    assert maps.tolist() == [[[0, 0, 0], [-1, 0, -1]],
                             [[2, 2, -1], [1, -1, -1]],
                             [[3, 3, 3], [-1, 3, -1]],
                             [[4, 5, 5], [4, 4, -1]]]
    # a level whose layer the bank does not have is empty and takes no rows
    maps, rows = langsplat_maps(layers[:1], (1, 0, 1, 2))
    assert rows.tolist() == [1, 3] and (maps[[0, 2, 3]] == -1).all() and maps[1].tolist() == [[1, 1, -1], [0, -1, -1]]


def test_export_follows_langsplat_layout(demo):
    root, scene_dir, bank_dir, features = demo
    bank = SegmentBank.open(bank_dir)
    regions = {r["id"]: r for r in json.loads((scene_dir / "regions.json").read_text())["regions"]}
    level_names = json.loads((scene_dir / "regions.json").read_text())["levels"]
    for i, stem in enumerate(bank.image_names):
        s = np.load(features / f"{stem}_s.npy")
        f = np.load(features / f"{stem}_f.npy")
        assert s.shape == (4, bank.height, bank.width) and f.dtype == np.float32
        assert f.shape[1] == 384
        # LangSplat preprocess.py's own checks: level j's indices follow the rows of the levels
        # before it, each level's last row appears, and the rows end with the last level.
        offset = 0
        for level in range(4):
            ids = np.unique(s[level][s[level] >= 0]).astype(int)
            assert ids.tolist() == list(range(offset, offset + len(ids)))
            offset += len(ids)
        assert offset == f.shape[0] == int(s.max()) + 1
        # each LangSplat level holds exactly the demo regions of its level, row by row
        rec = bank.record(i)
        src = np.asarray(bank.optional(i, "source_ids"))
        gt_masks = rec.masks()
        for level, name in enumerate(EXPORTED_LEVELS):
            want = [k for k in range(rec.num_segments) if regions[int(src[k])]["level"] == level_names.index(name)]
            got = np.unique(s[level][s[level] >= 0]).astype(int)
            assert len(got) == len(want)
            for row, k in zip(got, want):  # rows follow the bank's order within a level
                assert np.array_equal(s[level] == row, gt_masks[k])
                np.testing.assert_array_equal(f[row], rec.embeddings[k].astype(np.float32))
    spec = json.loads((features / "encoder.json").read_text())
    assert spec["name"] == "captions" and spec["levels"] == {"default": 1, "s": 0, "m": 1, "l": 2}


def test_export_import_round_trip(demo):
    root, scene_dir, bank_dir, features = demo
    back = root / "bank_back"
    _cli("segments-from-langsplat", scene_dir, "--features", features, "--encoder", "captions",
         "--depth-source", "gt", "--out", back, "--quiet")
    bank, again = SegmentBank.open(bank_dir), SegmentBank.open(back)
    spec = again.encoder_spec
    assert spec["name"] == "captions" and spec["embed_dim"] == 384
    assert "all-MiniLM-L6-v2" in spec["description"] and "stand-in for CLIP" in spec["description"]
    assert get_encoder(spec).dim == again.embed_dim  # queries get the matching text encoder
    level_layer = {"part": 0, "object": 1, "group": 2}
    total = 0
    for i in range(bank.num_images):
        a, b = bank.record(i), again.record(i)
        a_layer = segment_layers(np.asarray(a.layers), a.num_segments)
        b_layer = segment_layers(np.asarray(b.layers), b.num_segments)
        a_masks, b_masks = a.masks(), b.masks()
        # the import's segments, level by level, are the bank's segments of the exported layer
        want = np.concatenate([np.flatnonzero(a_layer == level_layer[n]) for n in EXPORTED_LEVELS])
        assert b.num_segments == len(want)
        assert b_layer.tolist() == np.repeat(np.arange(4), [np.sum(a_layer == level_layer[n])
                                                            for n in EXPORTED_LEVELS]).tolist()
        np.testing.assert_array_equal(b_masks, a_masks[want])
        np.testing.assert_array_equal(b.embeddings, a.embeddings[want])  # float16 both ways
        np.testing.assert_array_equal(b.areas, a.areas[want])
        # same masks, same exact depth: the same lifted scales
        np.testing.assert_allclose(b.scales, a.scales[want], rtol=1e-6, equal_nan=True)
        total += b.num_segments
    assert total == again.counts["segments"] > bank.counts["segments"]  # objects appear twice


def test_import_rejects_features_of_another_encoder(demo, capsys):
    root, scene_dir, bank_dir, features = demo
    rc = main(["segments-from-langsplat", str(scene_dir), "--features", str(features), "--encoder", "clip",
               "--depth-source", "gt", "--out", str(root / "bank_clip"), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2 and "_f.npy" in err and "384-d" in err and "512-d" in err
    # and the file itself reads back as LangSplat's layout
    layers, emb = read_langsplat(features, "frame_00001", 60, 80)
    assert layers.shape == (4, 60, 80) and emb.shape[1] == 384


def test_run_on_nerfstudio_scene_with_langsplat_features(demo, tmp_path, capsys):
    root, scene_dir, bank_dir, features = demo
    data = nerfstudio_langsplat_scene(scene_dir, features, tmp_path / "ns_scene")
    scene = load_scene(data)
    assert scene.source_format == "nerfstudio" and scene.ground_truth is None and scene.points is not None
    assert not (data / "sparse").exists() and not (data / "queries.json").exists()
    run = tmp_path / "run"
    small = ["--fit-steps", 40, "--train-steps", 60, "--dim", 32, "--quiet"]
    _cli("run", data, "--out", run, "--langsplat-features", data / "language_features", "--encoder", "captions",
         *small)
    stages = json.loads((run / "stages.json").read_text())
    assert list(stages) == ["fit-gaussians", "segments", "train", "eval"]
    bank = SegmentBank.open(run / "bank")
    assert bank.encoder_spec["name"] == "captions" and bank.segmenter_spec["name"] == "langsplat"
    assert bank.meta["lifting"]["depth_source"] == "render"  # no ground-truth depth in this scene
    assert bank.meta["lifting"]["scale_measure"] == "area"  # the cpu preset's
    result = json.loads((run / "eval" / "eval.json").read_text())
    for mode in ("composite", "explicit", "oracle"):
        score = result["scores"][mode]["exact"]
        assert score["num_pairs"] > 0 and np.isfinite(score["miou"]) and 0 <= score["miou"] <= 1
    assert set(result["query_types"].values()) == {"unknown"}  # no queries.json: no simple/compound split
    capsys.readouterr()

    # Unchanged inputs: every stage is skipped. --encoder is left out this time: the default
    # with --langsplat-features is the encoder the export recorded (captions), the same key.
    _cli("run", data, "--out", run, "--langsplat-features", data / "language_features", *small)
    out = capsys.readouterr().out
    for stage in stages:
        assert f"[{stage}] up to date" in out
    assert json.loads((run / "stages.json").read_text()) == stages


def test_scale_measure_follows_the_preset(tmp_path):
    from n2f2.pipeline import RunOptions, resolve_defaults

    def measure(**kw):
        return resolve_defaults(RunOptions(data=tmp_path, out=tmp_path / "run", **kw)).scale_measure

    assert measure() == "area"
    assert measure(preset="paper") == "eigenvalue"
    assert measure(preset="paper", scale_measure="extent") == "extent"
    assert measure(scale_measure="eigenvalue") == "eigenvalue"
