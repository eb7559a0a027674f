"""The 3D-OVS layout through ``n2f2``: ``export-ovs3d`` writes a generated scene in it (the masks
read back equal the scene's region maps), and ``n2f2 eval`` recognises the layout and scores the
tiny trained run with the 3D-OVS protocol."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from n2f2.cli import main as cli_main
from n2f2.errors import InputError
from n2f2.eval.ovs3d import export_ovs3d, ovs3d_labels_path, read_ovs3d_segmentations


@pytest.fixture(scope="module")
def exported(trained_run, tmp_path_factory):
    out = tmp_path_factory.mktemp("ovs3d") / "scene"
    assert cli_main(["export-ovs3d", str(trained_run.scene_dir), str(out)]) == 0
    return out


def _object_regions(scene_dir) -> dict[str, int]:
    """name -> id of the object-level regions, read straight from regions.json."""
    data = json.loads((scene_dir / "regions.json").read_text())
    level = data["levels"].index("object")
    return {r["name"]: r["id"] for r in data["regions"] if r["level"] == level}


def test_export_reads_back_as_the_region_maps(trained_run, exported):
    regions = _object_regions(trained_run.scene_dir)
    labelled = json.loads((trained_run.scene_dir / "scene.json").read_text())["labelled_views"]
    labels = read_ovs3d_segmentations(exported)
    assert labels.classes == sorted(regions)
    assert [v.view_index for v in labels.views] == sorted(labelled)
    images = sorted(p.stem for p in (trained_run.scene_dir / "images").iterdir())
    level = json.loads((trained_run.scene_dir / "regions.json").read_text())["levels"].index("object")
    for view in labels.views:
        ids = np.load(trained_run.scene_dir / "regions" / f"{images[view.view_index]}.npy")[level]
        for k, name in enumerate(labels.classes):
            assert np.array_equal(view.masks[k], ids == regions[name]), (view.name, name)
    # The copy is a scene of its own, in the same view order, without the ground truth.
    from n2f2.data import load_scene

    scene = load_scene(exported)
    assert scene.image_names == images and scene.ground_truth is None
    assert ovs3d_labels_path(exported) == exported / "segmentations"
    assert ovs3d_labels_path(trained_run.scene_dir) is None


def test_export_bad_input(trained_run, exported, tmp_path):
    with pytest.raises(InputError, match="level"):
        export_ovs3d(trained_run.scene_dir, tmp_path / "a", level="room")
    with pytest.raises(InputError, match="not in the scene"):
        export_ovs3d(trained_run.scene_dir, tmp_path / "b", views=[trained_run.num_views])
    with pytest.raises(InputError, match="regions.json"):
        export_ovs3d(exported, tmp_path / "c")  # no ground truth to export
    with pytest.raises(InputError, match="already holds"):
        export_ovs3d(trained_run.scene_dir, exported)
    info = export_ovs3d(trained_run.scene_dir, tmp_path / "d", level="part", views=[0, 2])
    assert info["views"] == [0, 2] and sorted(p.name for p in (tmp_path / "d" / "segmentations").iterdir()) == [
        "00",
        "02",
        "classes.txt",
    ]


def test_eval_detects_the_layout_and_scores(trained_run, exported, tmp_path, capsys):
    out = tmp_path / "eval"
    argv = ["eval", str(trained_run.run_dir), "--labels", str(exported), "--scene", str(exported)]
    assert cli_main(argv + ["--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    data = json.loads((out / "eval.json").read_text())
    assert data["format"] == "n2f2-eval-ovs3d-v1" and data["prediction"] == "argmax"
    assert data["modes"] == ["composite", "explicit", "soft"]  # oracle has no 3D-OVS reading
    n_views = len(read_ovs3d_segmentations(exported).views)
    for m in data["modes"]:
        for b in ("exact", "scaled"):
            s = data["scores"][m][b]
            assert 0.0 <= s["miou"] <= 1.0 and 0.0 <= s["accuracy"] <= 1.0
            assert len(s["per_view"]) == n_views and sorted(s["per_class_iou"]) == data["classes"]
            ious = np.array([v["iou"] for v in s["per_view"]])
            assert s["miou"] == pytest.approx(ious.mean())  # mean over (view, class) pairs
    shown = re.findall(r"eval 3D-OVS composite: exact: mIoU ([0-9.]+)%", printed)
    assert shown and 0.0 <= float(shown[0]) <= 100.0
    assert "3D-OVS" in (out / "eval.md").read_text()

    # Threshold prediction; flags of the LERF-OVS protocols are refused.
    out2 = tmp_path / "eval2"
    assert cli_main(argv + ["--out", str(out2), "--quiet", "--mode", "composite", "--ovs-prediction", "threshold"]) == 0
    s = json.loads((out2 / "eval.json").read_text())["scores"]["composite"]["exact"]
    assert s["accuracy"] is None and 0.0 <= s["miou"] <= 1.0
    assert cli_main(argv + ["--out", str(tmp_path / "x"), "--protocol", "2d"]) == 2
    assert "3d-ovs" in capsys.readouterr().err
    assert cli_main(argv + ["--out", str(tmp_path / "x"), "--budget"]) == 2
    assert "--budget" in capsys.readouterr().err
