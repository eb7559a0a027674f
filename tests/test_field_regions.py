"""benchmarks/field_regions.py, the check of which ground-truth regions the field keeps apart:
Gaussians on a generated scene's surfaces get the regions its maps show there, and the scan of
scales and the per-level IoU agree with answers worked out by hand."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import torch

SCRIPT = Path(__file__).resolve().parents[1] / "benchmarks" / "field_regions.py"


@pytest.fixture(scope="module")
def tool():
    spec = importlib.util.spec_from_file_location("field_regions", SCRIPT)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_gaussians_on_surfaces_get_the_regions_the_maps_show(tool, tmp_path):
    from n2f2.data import load_scene
    from n2f2.data.synthetic import generate_demo_scene

    scene = tmp_path / "scene"
    generate_demo_scene(scene, num_views=4, width=64, height=48, seed=0, show_progress=False)
    cams = load_scene(scene).cameras
    stem = "frame_00002"
    cam = cams[1]
    ids = np.load(scene / "regions" / f"{stem}.npy")  # [3, H, W]
    depth = np.load(scene / "depth" / f"{stem}.npy")
    # pixels whose 5 x 5 neighbourhood has one object id: other views see the same region there
    h, w = depth.shape
    rows, cols = [], []
    for v in range(2, h - 2, 3):
        for u in range(2, w - 2, 3):
            if (ids[1, v - 2 : v + 3, u - 2 : u + 3] == ids[1, v, u]).all() and ids[1, v, u] >= 0:
                rows.append(v)
                cols.append(u)
    rows, cols = np.array(rows), np.array(cols)
    z = depth[rows, cols]
    pc = np.stack([(cols + 0.5 - cam.cx) / cam.fx * z, (rows + 0.5 - cam.cy) / cam.fy * z, z], 1)
    points = (pc - cam.t) @ cam.R  # camera to world: R^T (p - t)
    regions = json.loads((scene / "regions.json").read_text())["regions"]
    floor = next(int(r["id"]) for r in regions if r["name"] == "floor")
    on_floor = ids[1, rows, cols] == floor
    assert on_floor.sum() >= 5
    under = points[on_floor] - np.array([0.0, 0.0, 0.5])  # half a metre under the floor: seen by no view
    far = np.array([[1e4, 1e4, 1e4]])  # in no view
    labels = tool.gaussian_regions(np.concatenate([points, under, far]), scene)
    n = len(points)
    assert labels.shape == (n + len(under) + 1, 3)
    assert (labels[n:] == -1).all()  # the depth test: under the floor projects onto floor pixels
    agree = (labels[:n, 1] == ids[1, rows, cols]).mean()
    assert agree > 0.95, agree  # majority over the views; a few points sit where views disagree
    assert (labels[:n, 2] == ids[2, rows, cols]).mean() > 0.95


def test_scan_counts_the_scales_at_which_two_regions_are_apart(tool):
    from n2f2.field.variants import get_variant

    variant = get_variant("nested")
    scales, labels = variant.coarse_to_fine(4, 1), variant.coarse_to_fine_labels(4, 1)
    theta = torch.zeros(6, 4)
    theta[0:2, 0] = 1.0  # region a: e1 at every prefix
    theta[2:4, 1] = 1.0  # region b: e2, zero at d = 1
    theta[4:6, 0] = 1.0  # region c: the same as a
    masks = {n: np.isin(np.arange(6), r) for n, r in (("a", [0, 1]), ("b", [2, 3]), ("c", [4, 5]))}
    rows = tool.scan_pairs(theta, torch.eye(4), scales, labels, masks, [("a", "b"), ("a", "c")])
    # a / b: at d = 1, b's features are zero: distance 1 over spreads 0 + 1 (not more than them);
    # from d = 2 on, orthogonal unit features with no spread
    assert rows[0]["apart_at"] == ["d=2", "d=3", "d=4"] and rows[0]["scales"] == 4
    assert rows[1]["apart_at"] == []  # identical features: distance 0


def test_level_ious_by_hand(tool):
    nodes = np.array([[0, 1], [0, 1], [0, 2], [3, 4], [3, 4]])  # [N, L]
    masks = {"r": np.array([1, 1, 1, 0, 0], bool), "s": np.array([0, 0, 1, 1, 0], bool)}
    labelled = np.array([1, 1, 1, 1, 1], bool)
    out = tool.level_ious(nodes, masks, labelled)
    assert out["r"] == [1.0, pytest.approx(2 / 3)]  # node 0 exactly; then node 1 (2 of 3)
    assert out["s"] == [pytest.approx(1 / 3), pytest.approx(1 / 2)]  # node 3: {3} of {2, 3, 4}; node 2: {2} of {2, 3}
    unlabelled = np.array([1, 1, 0, 1, 1], bool)  # Gaussian 2 out: r is {0, 1}, node 1 is {0, 1}
    assert tool.level_ious(nodes, {"r": masks["r"]}, unlabelled)["r"] == [1.0, 1.0]
