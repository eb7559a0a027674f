"""``n2f2 eval-hierarchy`` on a hand-built decomposition and ground truth (20x20 views) whose
answers are worked out by hand: best IoUs per region and kind, the cross-view consistency over
three views, a planted nesting violation, the resize of a larger region map, the 2D baseline on
flat-coloured blocks, and the one-line refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from n2f2.cli import main as cli_main
from n2f2.errors import InputError
from n2f2.eval.hierarchy import best_matches, consistency, evaluate_hierarchy, nesting_violations

H = W = 20
PART_A, PART_B, PART_C, OBJ_O, OBJ_P, GROUP_G = 10, 11, 12, 20, 21, 30


def ground_truth() -> np.ndarray:  # [3, H, W] int32
    """Parts A (rows 0-9, cols 0-9) and B (rows 0-9, cols 10-19), a small part C (50 px, below
    the 100 px threshold), objects O (rows 0-9) and P (rows 10-19), the group G (all)."""
    gt = np.full((3, H, W), -1, np.int32)
    gt[0, :10, :10], gt[0, :10, 10:], gt[0, 10:15, :10] = PART_A, PART_B, PART_C
    gt[1, :10], gt[1, 10:] = OBJ_O, OBJ_P
    gt[2] = GROUP_G
    return gt


def node_levels(swap: bool = False) -> np.ndarray:  # [2, H, W] int32
    """Level 0: node 0 (cols 0-14), node 5 (cols 15-19). Level 1: node 1 (rows 0-9, cols 0-9),
    node 2 (rows 0-4, cols 10-19), node 3 (rows 5-19, cols 10-19), node 4 (rows 10-19, cols 0-9);
    ``swap`` exchanges nodes 1 and 4."""
    levels = np.full((2, H, W), -1, np.int32)
    levels[0, :, :15], levels[0, :, 15:] = 0, 5
    one, four = (4, 1) if swap else (1, 4)
    levels[1, :10, :10], levels[1, :5, 10:], levels[1, 5:, 10:], levels[1, 10:, :10] = one, 2, 3, four
    return levels


def image() -> np.ndarray:  # [H, W, 3] uint8: A red, B green, rows 10-19 blue
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[:10, :10], rgb[:10, 10:], rgb[10:] = (220, 30, 30), (30, 200, 40), (30, 40, 210)
    return rgb


TREE = {
    "format": "n2f2-tree-v1",
    "num_levels": 2,
    "levels": [
        {"level": 0, "scale": 1.0, "scale_label": "coarse", "nodes": 2},
        {"level": 1, "scale": 0.5, "scale_label": "fine", "nodes": 4},
    ],
    "nodes": [
        {
            "id": i,
            "parent": p,
            "level": lv,
            "scale": 1.0,
            "gaussians": 1,
            "centroid": [0, 0, 0],
            "box": [[0, 0, 0], [1, 1, 1]],
            "text": None,
            "relevancy": None,
        }
        for i, p, lv in [(0, None, 0), (5, None, 0), (1, 0, 1), (2, 0, 1), (3, 0, 1), (4, 0, 1)]
    ],
}
# Gaussian 3 is in node 3 but in node 5 one level up, not node 3's parent 0: node 3 does not nest.
GAUSSIAN_NODES = np.array([[0, 1], [0, 2], [0, 3], [5, 3], [0, 4], [5, -1]], np.int32)
VIEWS = ["frame_00001", "frame_00002", "frame_00003"]  # frame_00004 is labelled but not decomposed


@pytest.fixture
def fake(tmp_path):
    """(run, decomp, scene) folders: frame_00003's nodes 1 and 4 swapped, and its region map at
    twice the size (nearest-neighbour resized back to 20x20, exactly)."""
    run, decomp, scene = tmp_path / "run", tmp_path / "decomp", tmp_path / "scene"
    run.mkdir()
    (decomp / "views").mkdir(parents=True)
    (decomp / "tree.json").write_text(json.dumps(TREE))
    np.save(decomp / "gaussian_nodes.npy", GAUSSIAN_NODES)
    (scene / "regions").mkdir(parents=True)
    (scene / "images").mkdir()
    regions = [
        {"id": r, "level": lv, "name": n, "caption": n, "parent": p, "pixels": 1}
        for r, lv, n, p in [
            (PART_A, 0, "a", OBJ_O),
            (PART_B, 0, "b", OBJ_O),
            (PART_C, 0, "c", OBJ_P),
            (OBJ_O, 1, "o", GROUP_G),
            (OBJ_P, 1, "p", GROUP_G),
            (GROUP_G, 2, "g", None),
        ]
    ]
    (scene / "regions.json").write_text(json.dumps({"levels": ["part", "object", "group"], "regions": regions}))
    for stem in [*VIEWS, "frame_00004"]:
        gt = ground_truth()
        np.save(scene / "regions" / f"{stem}.npy", gt.repeat(2, 1).repeat(2, 2) if stem == VIEWS[2] else gt)
        Image.fromarray(image()).save(scene / "images" / f"{stem}.png")
    for stem in VIEWS:
        (decomp / "views" / stem).mkdir()
        np.save(decomp / "views" / stem / "levels.npy", node_levels(swap=stem == VIEWS[2]))
    return run, decomp, scene


def test_best_matches_by_hand():
    found = best_matches(ground_truth(), node_levels(), min_pixels=100)
    got = {rid: (pixels, round(m.iou, 6), m.segment, m.layer) for (_, rid), (pixels, m) in found.items()}
    assert got == {
        PART_A: (100, 1.0, 1, 1),  # node 1 is A
        PART_B: (100, 0.5, 2, 1),  # node 2 covers half of B and nothing else
        OBJ_O: (200, 0.5, 1, 1),  # node 1: 100 / 200 (node 0: 150 / 350)
        OBJ_P: (200, 0.5, 4, 1),  # node 4: 100 / 200 (node 3: 100 / 250)
        GROUP_G: (400, 0.75, 0, 0),  # node 0: 300 / 400
    }  # C has 50 px: not counted
    assert {k for k, _ in found} == {0, 1, 2} and all(m.tied == [m.segment] for _, m in found.values())
    # A tie: node 7 at level 0 is exactly A too; the coarser level wins, both are kept.
    levels = node_levels()
    levels[0, :10, :10] = 7
    _, match = best_matches(ground_truth(), levels, min_pixels=100)[(0, PART_A)]
    assert (match.iou, match.segment, match.layer, match.tied) == (1.0, 7, 0, [7, 1])


def test_consistency_counts_tied_nodes():
    views = {(0, 1): [[4], [4, 9], [9]], (1, 2): [[3], []], (1, 5): [[6]]}  # region 5: one view only
    c = consistency(views, ["part", "object"])
    assert [(r["region"], r["mode_node"], r["share"]) for r in c["per_region"]] == [(1, 4, 2 / 3), (2, 3, 0.5)]
    assert (c["regions"], c["mean"], c["per_kind"]["object"]["mean"]) == (2, (2 / 3 + 0.5) / 2, 0.5)


def test_nesting_counts_the_planted_violation():
    n = nesting_violations(TREE, GAUSSIAN_NODES)
    assert (n["nodes"], n["violations"], n["share"], n["violating_nodes"], n["empty_nodes"]) == (4, 1, 0.25, [3], 0)
    orphan = {**TREE, "nodes": [*TREE["nodes"], {"id": 9, "parent": None, "level": 1}]}  # no parent, no Gaussians
    n = nesting_violations(orphan, GAUSSIAN_NODES)
    assert (n["nodes"], n["violations"], n["violating_nodes"], n["empty_nodes"]) == (5, 2, [3, 9], 1)


def test_a_node_spanning_two_levels_nests_in_itself():
    # Gaussians 0-1 in node 0 at both levels (unsplit), 2-3 in node 1, split into 2 and 3.
    ids = np.array([[0, 0], [0, 0], [1, 2], [1, 3]])
    tree = {"nodes": [{"id": 0, "parent": None, "level": 0, "last_level": 1},
                      {"id": 1, "parent": None, "level": 0}, {"id": 2, "parent": 1, "level": 1},
                      {"id": 3, "parent": 1, "level": 1}]}
    n = nesting_violations(tree, ids)
    assert (n["nodes"], n["violations"]) == (2, 0)
    ids[1, 1] = 2  # Gaussian 1 moves to node 2, whose parent is 1: node 2 no longer nests
    assert nesting_violations(tree, ids)["violating_nodes"] == [2]


def test_evaluation_by_hand(fake, tmp_path):
    run, decomp, scene = fake
    lines = []
    result = evaluate_hierarchy(run, decomp, scene, log=lines.append)
    out = decomp / "eval_hierarchy"
    h, b = result["hierarchy"], result["baseline"]
    # Every view has the same best IoUs (the swap moves ids, not masks).
    means = {k: (v["regions"], round(v["mean_best_iou"], 6)) for k, v in h["best_iou"].items()}
    assert means == {"part": (6, 0.75), "object": (6, 0.5), "group": (3, 0.75), "all": (15, 0.65)}
    view3 = {r["region"]: r["best_node"] for r in result["per_view"][VIEWS[2]]["regions"]}
    assert all(r["tied_nodes"] == [] for v in result["per_view"].values() for r in v["regions"])
    assert view3 == {PART_A: 4, PART_B: 2, OBJ_O: 4, OBJ_P: 1, GROUP_G: 0}
    # Consistency: A, O and P keep their best node in 2 of 3 views; B and G in all 3.
    c = h["consistency"]
    assert (c["regions"], round(c["mean"], 6)) == (5, 0.8)
    assert round(c["per_kind"]["part"]["mean"], 6) == round(5 / 6, 6) and c["per_kind"]["group"]["mean"] == 1.0
    assert (h["nesting"]["violations"], h["nesting"]["share"], h["num_levels"]) == (1, 0.25, 2)
    # The 2D baseline finds the flat-coloured parts exactly; its consistency is not defined.
    assert b["best_iou"]["part"]["mean_best_iou"] == 1.0 and b["best_iou"]["all"]["regions"] == 15
    assert all(0.0 <= v["mean_best_iou"] <= 1.0 for v in b["best_iou"].values()) and b["consistency"] is None
    assert result["views"] == {"labelled": 4, "evaluated": VIEWS, "skipped": ["frame_00004"]}
    assert any("resized (nearest) from 40x40 to 20x20 in 1 view" in n for n in result["notes"])
    # The files: the JSON holds the same numbers, the table every kind, the plot its values.
    saved = json.loads((out / "eval_hierarchy.json").read_text())
    assert saved["hierarchy"]["best_iou"] == h["best_iou"] and saved["plot"]["values"]["3D hierarchy"]["part"] == 0.75
    md = (out / "eval_hierarchy.md").read_text()
    assert "| part | 6 | 75.0 | 100.0 |" in md and "| all | 15 | 65.0 |" in md and "80.0 %" in md
    assert (out / "eval_hierarchy.png").stat().st_size > 0
    assert len(lines) == 1 and lines[0].startswith("eval-hierarchy: 3 views, 15 regions: mean best IoU 3D 65.0%")
    with pytest.raises(InputError, match="already holds"):
        evaluate_hierarchy(run, decomp, scene, log=lines.append)


def test_cli_runs_and_refuses_in_one_line(fake, tmp_path, capsys):
    run, decomp, scene = fake
    argv = ["eval-hierarchy", str(run), str(decomp), "--labels", str(scene)]
    assert cli_main([*argv, "--out", str(tmp_path / "o"), "--min-pixels", "150"]) == 0
    saved = json.loads((tmp_path / "o" / "eval_hierarchy.json").read_text())
    assert saved["hierarchy"]["best_iou"]["all"]["regions"] == 9  # only O, P, G have >= 150 px
    assert capsys.readouterr().out.startswith("eval-hierarchy: 3 views, 9 regions")

    (decomp / "tree.json").unlink()
    assert cli_main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("n2f2 eval-hierarchy: error:") and "tree.json" in err
    assert "n2f2 decompose" in err and not (decomp / "eval_hierarchy").exists()

    (decomp / "tree.json").write_text(json.dumps(TREE))
    for stem in VIEWS:
        (decomp / "views" / stem / "levels.npy").unlink()
    assert cli_main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--views all" in err

    assert cli_main(["eval-hierarchy", str(run), str(decomp), "--labels", str(run)]) == 2
    assert "no ground-truth regions" in capsys.readouterr().err


def test_a_ground_truth_bank_scores_as_the_labels_do(trained_run, tmp_path):
    """--segments BANK: on a bank of the ground-truth segmenter the segments are the labelled
    regions, so every view's (pixels, best IoU) pairs equal the --labels evaluation's; kinds are
    the thirds of each segment's quantised scale, and consistency is not defined."""
    from n2f2.segments.bank import SegmentBank

    run, scene, bank = trained_run.run_dir, trained_run.scene_dir, trained_run.bank_dir
    decomp = tmp_path / "dec"
    assert cli_main(["decompose", str(run), "--out", str(decomp), "--views", "all", "--quiet"]) == 0
    by_labels = evaluate_hierarchy(run, decomp, scene, out=tmp_path / "l", log=lambda s: None)
    lines = []
    by_bank = evaluate_hierarchy(run, decomp, segments=bank, out=tmp_path / "s", log=lines.append)
    assert by_bank["regions"] == "segments" and by_labels["regions"] == "labels"
    assert by_bank["kinds"] == ["small", "medium", "large"]
    views = by_labels["views"]["evaluated"]
    assert views and set(views) <= set(by_bank["views"]["evaluated"])
    for stem in views:
        want = sorted((r["pixels"], round(r["best_iou"], 12)) for r in by_labels["per_view"][stem]["regions"])
        got = sorted((r["pixels"], round(r["best_iou"], 12)) for r in by_bank["per_view"][stem]["regions"])
        assert got == want, stem
    sb = SegmentBank.open(bank)
    ids = [r["region"] for v in by_bank["per_view"].values() for r in v["regions"]]
    assert len(ids) == len(set(ids))  # one id per segment of a view, none shared between views
    for stem, view in by_bank["per_view"].items():
        q = sb.record(sb.index(stem)).quantized
        for r in view["regions"]:
            s = int(r["name"].rsplit(" ", 1)[1])  # "<stem> segment <s>"
            assert r["name"].startswith(stem)
            assert r["kind"] == ("small" if q[s] < 1 / 3 else "medium" if q[s] < 2 / 3 else "large")
    assert by_bank["hierarchy"]["consistency"]["regions"] == 0
    md = (tmp_path / "s" / "eval_hierarchy.md").read_text()
    assert "segments of the segment bank" in md and "not ground truth" in md
    assert len(lines) == 1 and "| small" not in lines[0] and lines[0].startswith("eval-hierarchy:")
