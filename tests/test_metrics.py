"""Retrieval metrics, per-query deltas and the report helpers, against hand-computed answers
and slow loop references."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from n2f2.eval.metrics import (per_query_scores, query_deltas, recall_at_k, segment_mean_relevancy,
                               segment_ranks)
from n2f2.eval.protocol import PairRecord, SceneScores
from n2f2.eval import reports


def test_segment_mean_relevancy_matches_loop():
    rng = np.random.default_rng(0)
    rel = rng.random((2, 7, 9))
    seg = rng.integers(-1, 5, size=(2, 7, 9))  # two nested layers, -1 = none
    means, areas = segment_mean_relevancy(rel, seg, num_segments=6)
    for s in range(6):
        pix = [(l, i, j) for l in range(2) for i in range(7) for j in range(9) if seg[l, i, j] == s]
        assert areas[s] == len(pix)
        for q in range(2):
            if pix:
                assert means[q, s] == pytest.approx(np.mean([rel[q, i, j] for _, i, j in pix]))
            else:
                assert np.isnan(means[q, s])
    assert np.isnan(means[:, 5]).all()  # id 5 never occurs
    single, _ = segment_mean_relevancy(rel[0], seg[0])
    assert single.shape == (5,)
    with pytest.raises(ValueError):
        segment_mean_relevancy(rel, seg.astype(float))
    with pytest.raises(ValueError):
        segment_mean_relevancy(rel, seg, num_segments=3)


def test_segment_ranks_count_ties_against():
    ranks = segment_ranks(np.array([0.9, 0.5, np.nan, 0.5, 0.1]))
    assert np.array_equal(ranks[[0, 1, 3, 4]], [1, 3, 3, 4]) and np.isnan(ranks[2])
    assert np.array_equal(segment_ranks(np.full(4, 0.3)), [4, 4, 4, 4])


def test_recall_at_k_by_hand():
    scores = np.array([
        [0.9, 0.8, 0.7, 0.6, 0.5],  # positives {1, 3}: ranks 2, 4
        [0.1, 0.2, 0.3, 0.4, 0.5],  # positive {4}: rank 1
        [0.5, 0.5, 0.5, 0.5, 0.5],  # constant map: rank 5, nothing retrieved
        [0.9, np.nan, 0.1, 0.2, 0.3],  # positive 1 absent from the pool: skipped
    ])
    r = recall_at_k(scores, [[1, 3], [4], [0], [1]], ks=(1, 3, 5), queries=["a", "b", "c", "d"])
    assert r.skipped == ["d"]
    per = {q.query: q for q in r.per_query}
    assert per["a"].recall == {1: 0.0, 3: 1 / 2, 5: 1.0} and per["a"].first_rank == 2
    assert per["b"].recall == {1: 1.0, 3: 1.0, 5: 1.0}
    assert per["c"].recall == {1: 0.0, 3: 0.0, 5: 1.0} and per["c"].first_rank == 5
    assert r.recall[1] == pytest.approx(1 / 3)
    assert r.recall[3] == pytest.approx((0.5 + 1 + 0) / 3)
    assert r.mean_first_rank == pytest.approx((2 + 1 + 5) / 3)
    assert r.pool_size == 5
    with pytest.raises(ValueError):
        recall_at_k(scores, [[9]] * 4)


def test_query_deltas_top_bottom():
    a = {"mug": 0.5, "cookies": 0.2, "bag of cookies": 0.1, "plate": 0.9, "knife": 0.4, "old": 0.3}
    b = {"mug": 0.6, "cookies": 0.1, "bag of cookies": 0.7, "plate": 0.9, "knife": 0.0, "new": 0.5}
    d = query_deltas(a, b, n=2)
    assert [x.query for x in d.top] == ["bag of cookies", "mug"]
    assert [x.query for x in d.bottom] == ["knife", "cookies"]
    assert d.top[0].delta == pytest.approx(0.6) and d.bottom[0].delta == pytest.approx(-0.4)
    assert d.mean_delta == pytest.approx((0.1 - 0.1 + 0.6 + 0.0 - 0.4) / 5)
    assert d.only_a == ["old"] and d.only_b == ["new"]
    with pytest.raises(ValueError):
        query_deltas({"x": float("nan")}, {"x": 1.0})


def _scores():
    pairs = [PairRecord("frame_00001", 0, "mug", 0.5, True, 0, 1, [0.5, 0.7], 30),
             PairRecord("frame_00002", 1, "mug", 0.3, False, 1, 1, [0.2, 0.3], 30),
             PairRecord("frame_00002", 1, "plate | dish", 0.9, True, 1, 0, [0.1, 0.9], 30)]
    return SceneScores(pairs, miou=float(np.mean([0.5, 0.3, 0.9])), loc_accuracy=2 / 3,
                       num_pairs=3, num_frames=2, box_sizes=[30], majority_radii=[3])


def test_per_query_scores():
    s = _scores()
    assert per_query_scores(s.pairs) == pytest.approx({"mug": 0.4, "plate | dish": 0.9})
    assert per_query_scores(s.pairs, "hit") == pytest.approx({"mug": 0.5, "plate | dish": 1.0})


def test_markdown_tables():
    t = reports.markdown_table(["a", "b"], [["x|y", 1]])
    assert t.splitlines() == ["| a | b |", "| :--- | ---: |", "| x\\|y | 1 |"]
    with pytest.raises(ValueError):
        reports.markdown_table(["a", "b"], [[1]])
    s = _scores()
    table = reports.scene_scores_table({"teatime": s, "ramen": s})
    lines = table.splitlines()
    assert lines[2].startswith("| teatime | 56.7 | 66.7 | 63.3 | 3 | 30 | 3 | 0 | 0 |")  # oracle (0.7+0.3+0.9)/3
    assert lines[-1].startswith("| **mean** | 56.7 | 66.7 |")
    pt = reports.pairs_table(s)
    assert "| frame_00002 | plate \\| dish | 90.0 | yes | 1 | 0 | 10.0 90.0 |" in pt
    dt = reports.deltas_table(query_deltas({"q": 0.2, "r": 0.5}, {"q": 0.5, "r": 0.4}, n=1))
    assert "| top | q | 20.0 | 50.0 | +30.0 |" in dt and "| bottom | r | 50.0 | 40.0 | -10.0 |" in dt


def test_plots_write_pngs(tmp_path):
    s = _scores()
    paths = [
        reports.plot_grouped_bars(tmp_path / "bars.png", {"N2F2": {"teatime": 0.6, "ramen": 0.5},
                                                          "LangSplat": {"teatime": 0.65}}),
        reports.plot_query_deltas(tmp_path / "d.png", query_deltas({"q": 0.2, "r": 0.5}, {"q": 0.5, "r": 0.4})),
        reports.plot_level_histogram(tmp_path / "sub" / "levels.png", s),
    ]
    for p in paths:
        with Image.open(p) as im:
            assert im.format == "PNG" and im.size[0] > 100 and im.size[1] > 100
    assert sorted(f.name for f in tmp_path.rglob("*")) == ["bars.png", "d.png", "levels.png", "sub"]
