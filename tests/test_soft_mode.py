"""The ``soft`` query mode (n2f2.query.soft): the formula on a hand-worked case, the engine's 2D
maps and 3D Gaussian relevancy against slow references written out here, ``n2f2 query --mode
soft``, and ``n2f2 eval`` reporting it without changing the other modes' numbers."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from n2f2.cli import main as cli_main
from n2f2.field.variants import VARIANTS
from n2f2.query.caches import build_prefix_cache, soft_scales
from n2f2.field.relevancy import relevancy
from n2f2.query.soft import SOFT_TEMPERATURE, soft_relevancy, soft_weights, weighed_scales

TAU = 0.01  # the definition's temperature


def _soft_reference(rel: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # [S, P] -> soft [P], peaks [S]
    """The definition written out, in float64: ``w = softmax(peak / tau)``, ``sum_s w_s rel_s``."""
    rel = rel.double()
    peaks = rel.amax(dim=1)
    e = torch.exp((peaks - peaks.max()) / TAU)
    w = e / e.sum()
    return (w[:, None] * rel).sum(dim=0), peaks


# ------------------------------------------------------------------------------ the formula
def test_hand_worked_two_scales_three_points():
    """Peaks 0.50 and 0.52: weights softmax(50, 52) = (1 / (1 + e^2), e^2 / (1 + e^2))
    = (0.1192029, 0.8807971); point 0: 0.30 x 0.1192029 + 0.52 x 0.8807971 = 0.4937754, point 1:
    0.50 x 0.1192029 + 0.10 x 0.8807971 = 0.1476812, point 2: 0.20 x 0.1192029 + 0.40 x 0.8807971
    = 0.3761594."""
    assert SOFT_TEMPERATURE == TAU
    rel = torch.tensor([[0.30, 0.50, 0.20], [0.52, 0.10, 0.40]])  # [S = 2, P = 3]
    soft, peaks = soft_relevancy(rel[:, None, :])  # one query
    torch.testing.assert_close(peaks, torch.tensor([[0.50, 0.52]]), rtol=0, atol=0)
    torch.testing.assert_close(soft_weights(peaks), torch.tensor([[0.1192029, 0.8807971]]), rtol=0, atol=1e-6)
    torch.testing.assert_close(soft, torch.tensor([[0.4937754, 0.1476812, 0.3761594]]), rtol=0, atol=1e-6)


def test_one_scale_is_the_map_itself_and_negligible_scales_are_named():
    rel = torch.tensor([[[0.3, 0.9, 0.1]], [[0.2, 0.4, 0.6]]]).transpose(0, 1)  # [S = 1, Q = 2, P = 3]
    soft, peaks = soft_relevancy(rel)
    assert bool((soft_weights(peaks) == 1.0).all())  # a flat field's one scale: weight exactly 1
    assert torch.equal(soft, rel[0])
    # Peaks 0.9, 0.5, 0.89: scale 1 weighs exp(-40) / (1 + exp(-1)) ~ 3e-18 < 2^-24 / 3, left out.
    w = soft_weights(torch.tensor([[0.9, 0.5, 0.89]]))
    assert weighed_scales(w).tolist() == [0, 2]
    other = soft_weights(torch.tensor([[0.5, 0.9, 0.5]]))  # weighs scale 1 only (e^-40 for the others)
    assert weighed_scales(other).tolist() == [1]
    assert weighed_scales(torch.cat([w, other])).tolist() == [0, 1, 2]  # kept when any query weighs it
    with pytest.raises(ValueError, match="positive"):
        soft_weights(torch.zeros(1, 2), 0.0)


def test_variants_that_answer_soft():
    assert "soft" in VARIANTS["nested"].modes and "soft" in VARIANTS["flat"].modes
    assert "soft" not in VARIANTS["levels"].modes


def _random_cache(step: int, N: int = 3000, D: int = 12, E: int = 10):
    g = torch.Generator().manual_seed(3)
    theta = torch.randn(N, D, generator=g)
    W = torch.randn(E, D, generator=g) / D**0.5
    unit = lambda x: x / x.norm(dim=-1, keepdim=True)  # noqa: E731
    texts, negs = unit(torch.randn(4, E, generator=g)), unit(torch.randn(3, E, generator=g))
    per_scale = torch.stack(  # [S, N, Q]: the relevancy at every scale, written out in float64
        [relevancy(theta[:, :d].double() @ W[:, :d].double().T, texts.double(), negs.double())
         for d in range(step, D + 1, step)]
    )
    return build_prefix_cache(theta, W, negs, step, chunk=700), texts, per_scale


@pytest.mark.parametrize("step", [1, 3])
def test_streamed_gaussian_path_equals_the_definition(step):
    """``soft_scales`` (peaks from the streamed margins, windows of points) against the definition
    on the relevancy at every scale, and against it on the cache's whole ``[S, Q, N]`` tensor."""
    cache, texts, per_scale = _random_cache(step)
    soft, peaks = soft_scales(cache, texts)
    # float32 peaks (~1e-7) divided by tau = 0.01 move the weights by ~1e-5 relative: the tolerance.
    for q in range(len(texts)):
        ref, ref_peaks = _soft_reference(per_scale[:, :, q])
        torch.testing.assert_close(peaks[q].double(), ref_peaks, rtol=0, atol=1e-6)
        torch.testing.assert_close(soft[q].double(), ref, rtol=0, atol=1e-5)
    full, full_peaks = soft_relevancy(cache.relevancy(texts))
    torch.testing.assert_close(peaks, full_peaks, rtol=0, atol=2.0**-24)
    torch.testing.assert_close(soft, full, rtol=0, atol=2.0**-22)


def test_left_out_scales_are_the_negligible_ones(monkeypatch):
    """With the bound raised to 0.3 (scales under 0.3 / S left out for every query), the streamed
    sum is the sum over the kept scales exactly, and within 0.3 of the sum over all."""
    from n2f2.query import soft as soft_module

    monkeypatch.setattr(soft_module, "NEGLIGIBLE_WEIGHT", 0.3)
    cache, texts, per_scale = _random_cache(1)
    soft, peaks = soft_scales(cache, texts)
    w = soft_weights(peaks).double()  # [Q, S]
    kept = (w >= 0.3 / w.shape[1]).any(dim=0)
    assert 0 < int(kept.sum()) < w.shape[1]
    for q in range(len(texts)):
        ref = (w[q, kept, None] * per_scale[kept, :, q]).sum(dim=0)
        torch.testing.assert_close(soft[q].double(), ref, rtol=0, atol=1e-6)
        assert float((soft[q].double() - _soft_reference(per_scale[:, :, q])[0]).abs().max()) <= 0.3


# ------------------------------------------------------------------------------ the engine
@pytest.fixture(scope="module")
def engine(trained_run):
    from n2f2.query.engine import QueryEngine

    return QueryEngine.from_run(trained_run.run_dir)


def _texts(trained_run):
    return [trained_run.part_query, "teapot", "red mug", "wooden table"]


def test_engine_2d_soft_equals_the_formula_on_the_oracle_maps(engine, trained_run):
    texts = _texts(trained_run)
    view = engine.render_view(1, modes=["soft", "oracle"], rgb=False)
    res = engine.query(view, texts, "soft")
    assert res.mode == "soft" and res.chosen == [None] * len(texts)
    assert res.scale_labels == engine.scale_labels and res.relevancy.shape == (len(texts), view.height, view.width)
    maps: dict[int, torch.Tensor] = {}

    def keep(rel, qi):  # rel [S, H, W]: the relevancy at every scale
        maps[qi] = rel.double().clone()
        return np.zeros(len(rel))

    engine.query(view, texts, "oracle", scorer=keep)
    blended = 0
    for q in range(len(texts)):
        rel = maps[q].flatten(1)  # [S, H W]
        ref, peaks = _soft_reference(rel)
        torch.testing.assert_close(res.relevancy[q].double().flatten(), ref, rtol=0, atol=1e-6)
        torch.testing.assert_close(res.scale_scores[q].double(), peaks, rtol=0, atol=0)
        w = torch.softmax(peaks / TAU, dim=0)
        blended += int((w > 0.01).sum() > 1)
    assert blended  # the test run has queries whose maps blend several scales


def test_engine_3d_soft_equals_the_formula_on_per_gaussian_relevancy(engine, trained_run):
    from n2f2.query.maps import normalized_for_threshold

    texts = _texts(trained_run)
    res = engine.query_gaussians(texts, "soft")
    assert res.chosen == [None] * len(texts) and res.relevancy.shape == (len(texts), engine.theta.shape[0])
    theta, W = engine.theta.double(), engine.W.double()
    emb, negs = engine.encode(texts).double(), engine.encode(list(engine.config.negatives)).double()
    per_scale = torch.stack([relevancy(theta[:, :d] @ W[:, :d].T, emb, negs) for d in engine.scale_dims])  # [S, N, Q]
    for q in range(len(texts)):
        ref, peaks = _soft_reference(per_scale[:, :, q])
        torch.testing.assert_close(res.scale_scores[q].double(), peaks, rtol=0, atol=1e-5)
        torch.testing.assert_close(res.relevancy[q].double(), ref, rtol=0, atol=1e-5)
    # select(..., mode="soft") applies the protocol rule to that relevancy.
    sel = engine.select(texts[1], mode="soft")
    want = normalized_for_threshold(res.relevancy[1].float().numpy()) > 0.4
    assert np.array_equal(sel.numpy(), want) and want.any()


def test_query_cli_soft(engine, trained_run, tmp_path):
    out = tmp_path / "q"
    rc = cli_main(["query", str(trained_run.run_dir), "teapot", "--views", "1", "--mode", "soft",
                   "--out", str(out), "--quiet"])
    assert rc == 0
    summary = json.loads((out / "query.json").read_text())
    rec = summary["views"][0]["queries"][0]
    assert summary["mode"] == "soft" and rec["chosen_scale"] is None
    assert len(rec["scale_scores"]) == len(engine.scale_dims)
    view = engine.render_view(1, modes=["soft"], rgb=False)
    want = engine.query(view, ["teapot"], "soft").relevancy[0].numpy()
    np.testing.assert_allclose(np.load(out / rec["files"]["relevancy"]), want, rtol=0, atol=1e-6)


# ------------------------------------------------------------------------------ n2f2 eval
def _json(x) -> str:
    return json.dumps(x, sort_keys=True, default=str)


def test_eval_reports_soft_and_leaves_the_other_modes_alone(engine, trained_run, tmp_path, capsys):
    from n2f2.data.labels import read_label_dir
    from n2f2.eval.protocol import ProtocolConfig, evaluate_scene
    from n2f2.eval.runner import EvalConfig, evaluate_run

    labels = trained_run.scene_dir / "label"
    out = tmp_path / "eval"
    assert cli_main(["eval", str(trained_run.run_dir), "--labels", str(labels), "--out", str(out),
                     "--no-relevancy", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "eval soft: exact: loc" in printed
    got = json.loads((out / "eval.json").read_text())
    assert got["modes"] == ["composite", "explicit", "soft", "oracle"]
    assert "\n| soft |" in (out / "eval.md").read_text()
    # Without soft: every number of the other modes is the same.
    old = evaluate_run(trained_run.run_dir, labels, config=EvalConfig(modes=("composite", "explicit", "oracle"),
                                                                     progress=False)).to_dict()
    old = json.loads(json.dumps(old, default=str))
    for key in ("scores", "split", "per_query", "ap", "kinds", "retrieval"):
        for m in ("composite", "explicit", "oracle"):
            assert _json(got[key][m]) == _json(old[key][m]), (key, m)
    # The soft row is the protocol on the engine's own soft maps (one map, both boxes).
    label_list = read_label_dir(labels)

    def soft_maps(i, categories):  # -> [1, K, H, W]
        view = engine.render_view(i, modes=["soft"], rgb=False)
        return engine.query(view, categories, "soft").relevancy[None].numpy()

    for b, cfg in (("exact", ProtocolConfig()), ("scaled", ProtocolConfig.scaled())):
        ref = evaluate_scene(soft_maps, label_list, trained_run.num_views, cfg, labels, progress=False)
        assert got["scores"]["soft"][b]["miou"] == pytest.approx(ref.miou, abs=1e-6)
        assert got["scores"]["soft"][b]["loc_accuracy"] == pytest.approx(ref.loc_accuracy, abs=1e-12)
