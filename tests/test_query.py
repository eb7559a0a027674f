"""Tests of the query stage: composite embedding maths, the relevancy definition, the fast paths
against slow references, 3D selection / PLY export, CLI bad input."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest
import torch

from n2f2.query.composite import (PAPER_TEMPERATURE, canonical_scores, composite_weights, prefix_dot,
                                  prefix_margin_at, prefix_margin_max, prefix_sq_norms, prefix_terms, prefix_weights,
                                  premultiply, temperature_name, to_blocks, unit_weights)
from n2f2.query.engine import QueryConfig
from n2f2.validate import composite_temperature
from n2f2.segments.bins import supervised_dims
from n2f2.query.caches import build_composite_cache, build_linear_cache, build_prefix_cache, select_scale
from n2f2.field.relevancy import normalize_features, relevancy

DT = torch.float64


def _unit(x: torch.Tensor) -> torch.Tensor:
    return x / x.norm(dim=-1, keepdim=True)


def _random_field(N=9, D=12, E=10, K=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    theta = torch.randn(N, D, generator=g, dtype=DT)
    W = torch.randn(E, D, generator=g, dtype=DT) / D ** 0.5
    canon = _unit(torch.randn(K, E, generator=g, dtype=DT))
    return theta, W, canon


def _prefix_features_direct(theta, W, d):  # phi_d = W[:, :d] theta[:d], one Gaussian at a time
    return torch.stack([W[:, :d] @ th[:d] for th in theta])


def _relevancy_literal(phi, texts, negatives):
    """LERF's definition written out: per negative a 2-way softmax, min of the positive prob."""
    phi = phi / phi.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    out = torch.empty(phi.shape[0], texts.shape[0], dtype=phi.dtype)
    for q, t in enumerate(texts):
        probs = []
        for c in negatives:
            pair = torch.stack([phi @ t, phi @ c], dim=-1)  # [P, 2]
            probs.append(torch.softmax(10 * pair, dim=-1)[:, 0])
        out[:, q] = torch.stack(probs, dim=-1).min(dim=-1).values
    return out


# ------------------------------------------------------------------------------ composite
@pytest.mark.parametrize("step", [1, 3, 5])
@pytest.mark.parametrize("temperature", [1.0, 0.05])
def test_gamma_cumsum_equals_direct_formula(step, temperature):
    theta, W, canon = _random_field()
    D = theta.shape[1]
    dims = supervised_dims(D, step)
    assert dims == [d for d in range(1, D + 1) if d % step == 0]
    # Direct per-d formula of paper Eq. 6: score_d = max_k (W[:, :d] Theta[:d]) . phi_canon_k.
    scores = torch.stack([(_prefix_features_direct(theta, W, d) @ canon.T).max(dim=-1).values
                          for d in dims], dim=-1)  # [N, S]
    gamma_direct = torch.softmax(scores / temperature, dim=-1)
    gamma = composite_weights(theta, W, canon, step, temperature)
    torch.testing.assert_close(canonical_scores(theta, W, canon, step), scores, rtol=0, atol=1e-12)
    torch.testing.assert_close(gamma, gamma_direct, rtol=0, atol=1e-12)
    # Premultiplied feature (Eq. 7): W Theta~ = sum_d gamma_d phi_d.
    comp_direct = sum(gamma_direct[:, [s]] * _prefix_features_direct(theta, W, d)
                      for s, d in enumerate(dims))
    tilde = premultiply(theta, W, canon, step, temperature, chunk=4)  # chunking crosses rows
    torch.testing.assert_close(tilde @ W.T, comp_direct, rtol=0, atol=1e-12)


def test_uniform_gamma_gives_mean_of_scale_features():
    theta, W, canon = _random_field(D=8)
    D = theta.shape[1]
    uniform = torch.full((theta.shape[0], D), 1.0 / D, dtype=DT)
    r = prefix_weights(uniform, D, 1)
    # Reversed cumsum of a uniform gamma is the ramp (D - j + 1) / D for j = 1..D.
    ramp = torch.arange(D, 0, -1, dtype=DT) / D
    torch.testing.assert_close(r, ramp.expand_as(r), rtol=0, atol=1e-15)
    expected = sum(_prefix_features_direct(theta, W, d) for d in range(1, D + 1)) / D
    torch.testing.assert_close((r * theta) @ W.T, expected, rtol=0, atol=1e-12)
    # A huge temperature makes gamma uniform: premultiply then gives the same mean.
    tilde = premultiply(theta, W, canon, 1, temperature=1e12)
    torch.testing.assert_close(tilde @ W.T, expected, rtol=0, atol=1e-9)
    # T = infinity is that limit exactly, without the canonical phrases: NaN phrases change nothing.
    nan_canon = torch.full_like(canon, float("nan"))
    torch.testing.assert_close(premultiply(theta, W, nan_canon, 1, temperature=math.inf) @ W.T, expected,
                               rtol=0, atol=1e-12)


def test_uniform_gamma_with_a_step_weighs_each_scale_equally():
    theta, W, canon = _random_field(D=10)
    gamma = composite_weights(theta, W, canon, 3, math.inf)  # scales d = 3, 6, 9 of D = 10
    torch.testing.assert_close(gamma, torch.full((theta.shape[0], 3), 1 / 3, dtype=DT), rtol=0, atol=1e-15)
    expected = sum(_prefix_features_direct(theta, W, d) for d in (3, 6, 9)) / 3
    torch.testing.assert_close(premultiply(theta, W, canon, 3, math.inf) @ W.T, expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize("step", [1, 3])
def test_unit_weights_give_the_mean_of_normalised_scale_features(step):
    theta, W, canon = _random_field(D=10)
    theta[0] = 0.0  # a point whose features are all zero: it adds nothing and stays finite
    dims = supervised_dims(10, step)
    unit = [_prefix_features_direct(theta, W, d) for d in dims]
    unit = [f / f.norm(dim=-1, keepdim=True).clamp_min(1e-12) for f in unit]
    expected = sum(unit) / len(dims)
    gamma = unit_weights(theta, W, step)
    assert gamma.shape == (theta.shape[0], len(dims))
    tilde = premultiply(theta, W, torch.full_like(canon, float("nan")), step, weights="unit", chunk=3)
    torch.testing.assert_close(tilde @ W.T, expected, rtol=0, atol=1e-12)
    assert torch.equal(tilde[0], torch.zeros_like(tilde[0]))
    with pytest.raises(ValueError, match="composite weights"):
        premultiply(theta, W, canon, step, weights="mean")
    with pytest.raises(ValueError, match="composite weights"):
        QueryConfig(composite_weights="mean")


def test_composite_temperature_option_names_and_default():
    assert QueryConfig().composite_weights == "unit"  # n2f2's default; Eq. 6 by name
    assert composite_temperature("paper") == 1.0 == PAPER_TEMPERATURE == QueryConfig().temperature
    assert composite_temperature("uniform") == math.inf
    assert composite_temperature("0.5") == 0.5
    for bad in ("0", "-2", "nan", "-inf", "warm"):
        with pytest.raises(argparse.ArgumentTypeError):
            composite_temperature(bad)
    assert temperature_name(math.inf) == "uniform" and temperature_name(1.0) == 1.0


def test_prefix_weights_with_step_zero_past_last_scale():
    gamma = torch.tensor([[0.2, 0.3, 0.5]], dtype=DT)  # scales d = 3, 6, 9 of D = 10, k = 3
    r = prefix_weights(gamma, 10, 3)
    expected = torch.tensor([[1.0] * 3 + [0.8] * 3 + [0.5] * 3 + [0.0]], dtype=DT)
    torch.testing.assert_close(r, expected, rtol=0, atol=1e-15)


@pytest.mark.parametrize("step", [1, 4])
def test_prefix_dot_and_norms_equal_direct(step):
    theta, W, _ = _random_field(N=6, D=13, E=7)
    g = torch.Generator().manual_seed(3)
    t = _unit(torch.randn(4, 7, generator=g, dtype=DT))
    blocks = to_blocks(theta, step)
    dots = prefix_dot(blocks, (t @ W).T)  # [S, Q, P]
    norms = prefix_sq_norms(blocks, W.T @ W)  # [S, P]
    for s, d in enumerate(supervised_dims(13, step)):
        phi = _prefix_features_direct(theta, W, d)
        torch.testing.assert_close(dots[s], (phi @ t.T).T, rtol=0, atol=1e-12)
        torch.testing.assert_close(norms[s], (phi ** 2).sum(-1), rtol=0, atol=1e-12)


# ------------------------------------------------------------------------------ relevancy
def test_relevancy_equals_literal_softmax_min():
    g = torch.Generator().manual_seed(1)
    phi = torch.randn(50, 16, generator=g, dtype=DT) * 3.0  # unnormalised on purpose
    texts = _unit(torch.randn(3, 16, generator=g, dtype=DT))
    negs = _unit(torch.randn(4, 16, generator=g, dtype=DT))
    torch.testing.assert_close(relevancy(phi, texts, negs), _relevancy_literal(phi, texts, negs),
                               rtol=0, atol=1e-12)
    # Scale invariance (features are normalised) and the zero feature's relevancy of 0.5.
    torch.testing.assert_close(relevancy(7.0 * phi, texts, negs), relevancy(phi, texts, negs))
    zero = relevancy(torch.zeros(2, 16, dtype=DT), texts, negs)
    assert torch.all(zero == 0.5)
    n = normalize_features(phi)
    torch.testing.assert_close(n.norm(dim=-1), torch.ones(50, dtype=DT))


def test_relevancy_is_high_for_the_matching_text():
    texts = torch.eye(4, dtype=DT)[:2]  # "a" = e0, "b" = e1
    negs = torch.eye(4, dtype=DT)[2:]  # negatives e2, e3
    phi = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]], dtype=DT)
    r = relevancy(phi, texts, negs)
    # cos 1 vs max-negative 0: sigmoid(10); cos 0 vs 0: 0.5.
    expected = torch.tensor([[1 / (1 + np.exp(-10)), 0.5], [0.5, 1 / (1 + np.exp(-10))]], dtype=DT)
    torch.testing.assert_close(r, expected)


# ------------------------------------------------------------------------------ fast paths
def _linear_renderer(P, N, seed=5):
    """Rendering is linear in the features: a fixed non-negative [P, N] blending matrix."""
    g = torch.Generator().manual_seed(seed)
    R = torch.rand(P, N, generator=g, dtype=DT) * (torch.rand(P, N, generator=g, dtype=DT) < 0.4)
    return R / R.sum(dim=1, keepdim=True).clamp_min(1.0)


def test_composite_fast_path_equals_slow_path():
    theta, W, canon = _random_field(N=20, D=12, E=10)
    g = torch.Generator().manual_seed(2)
    texts = _unit(torch.randn(3, 10, generator=g, dtype=DT))
    negs = _unit(torch.randn(4, 10, generator=g, dtype=DT))
    R = _linear_renderer(30, 20)
    tilde = premultiply(theta, W, canon, 1, 1.0)
    fast = build_composite_cache(R @ tilde, W, negs, chunk=7).relevancy(texts)[0]  # [Q, P]
    # Slow: render the composite embedding itself (E channels), then relevancy.
    comp = R @ (tilde @ W.T)
    torch.testing.assert_close(fast, _relevancy_literal(comp, texts, negs).T, rtol=0, atol=1e-10)


@pytest.mark.parametrize("step", [1, 5])
def test_explicit_fast_path_equals_per_scale_slow_path(step):
    theta, W, _ = _random_field(N=20, D=12, E=10)
    g = torch.Generator().manual_seed(4)
    texts = _unit(torch.randn(2, 10, generator=g, dtype=DT))
    negs = _unit(torch.randn(4, 10, generator=g, dtype=DT))
    R = _linear_renderer(25, 20)
    rendered = R @ theta
    fast = build_prefix_cache(rendered, W, negs, step, chunk=6).relevancy(texts)  # [S, Q, P]
    dims = supervised_dims(12, step)
    assert fast.shape == (len(dims), 2, 25)
    for s, d in enumerate(dims):
        phi = rendered[:, :d] @ W[:, :d].T
        torch.testing.assert_close(fast[s], _relevancy_literal(phi, texts, negs).T, rtol=0, atol=1e-10)


def test_levels_fast_path_equals_slow_path():
    theta, W, _ = _random_field(N=20, D=12, E=10)
    g = torch.Generator().manual_seed(6)
    maps = torch.zeros(3, 10, 12, dtype=DT)
    for level, (a, b) in enumerate([(8, 12), (4, 8), (0, 4)]):
        maps[level, :, a:b] = W[:, a:b]
    texts = _unit(torch.randn(2, 10, generator=g, dtype=DT))
    negs = _unit(torch.randn(4, 10, generator=g, dtype=DT))
    rendered = _linear_renderer(25, 20) @ theta
    fast = build_linear_cache(rendered, maps, negs, ["part", "object", "group"], chunk=9).relevancy(texts)
    for level in range(3):
        phi = rendered @ maps[level].T
        torch.testing.assert_close(fast[level], _relevancy_literal(phi, texts, negs).T, rtol=0, atol=1e-10)


# ------------------------------------------------------------------------------ explicit selection
def _explicit_reference(theta, W, texts, negatives, dims):  # -> relevancy [S, Q, P] in float64
    """Relevancy at every scale, written out: ``phi_d`` grown block by block (so a zero block of
    theta leaves it exactly as it was and the scales tie exactly), scored by the literal
    softmax-and-min definition."""
    theta, W = theta.double(), W.double()
    phi = torch.zeros(theta.shape[0], W.shape[0], dtype=DT)
    out, prev = [], 0
    for d in dims:
        phi = phi + theta[:, prev:d] @ W[:, prev:d].T
        prev = d
        out.append(_relevancy_literal(phi, texts.double(), negatives.double()).T)
    return torch.stack(out)


def _assert_choice(chosen, ref_scores, tol=1e-6):  # chosen: Q ints; ref_scores [Q, S] float64
    """Each chosen scale is a best scale of the reference (up to float32 rounding), and the first
    one when the reference's best scales are one scale or an exact tie."""
    for q, c in enumerate(chosen):
        best = ref_scores[q].max()
        assert ref_scores[q, c] >= best - tol
        near = (ref_scores[q] >= best - tol).nonzero().flatten()
        if bool((ref_scores[q, near] == best).all()):
            assert c == int(near[0])


def _assert_same_as_full(chosen, scores, rel, full):  # [Q], [Q, S], [Q, P]; full [S, Q, P]
    """The streamed selection equals the one made on the cache's whole ``[S, Q, P]`` relevancy."""
    full_scores = full.amax(dim=-1).T
    assert chosen.tolist() == full_scores.argmax(dim=1).tolist()
    ulp = 2.0 ** -24  # torch's sigmoid may round the last few elements of a call differently
    torch.testing.assert_close(scores, full_scores, rtol=0, atol=ulp)
    torch.testing.assert_close(rel, full[chosen, torch.arange(len(chosen))], rtol=0, atol=ulp)


@pytest.mark.parametrize("step", [1, 3])
@pytest.mark.parametrize("compiled", [True, False])
def test_prefix_margins_equal_the_full_tensor_and_direct(step, compiled, monkeypatch):
    """The streamed per-scale maxima and chosen-scale margins equal the score caches' ``[S, Q, P]``
    margins bit for bit (compiled kernels or torch, one thread or two) and a direct computation."""
    from n2f2.query import composite

    monkeypatch.setattr(composite, "MARGIN_CHUNK", 64)  # several windows in the torch path
    theta, W, _ = _random_field(N=300, D=12, E=10)
    g = torch.Generator().manual_seed(8)
    texts = _unit(torch.randn(3, 10, generator=g, dtype=DT)).float()
    negs = _unit(torch.randn(4, 10, generator=g, dtype=DT)).float()
    theta, W = theta.float(), W.float()
    scales = torch.tensor([12 // step - 1, 0, 6 // step])

    def streamed_and_full(theta):  # -> (max [S, Q], at [Q, P]) streamed, and the [S, Q, P] margins
        cache = build_prefix_cache(theta, W, negs, step)
        S, k, _ = cache.blocks.shape
        q = (texts @ W[:, : S * k]).T
        terms = prefix_terms(cache.blocks, q)
        mx = prefix_margin_max(*terms, cache.inv_norm, cache.neg_max, compiled=compiled)
        at = prefix_margin_at(*terms, cache.inv_norm, cache.neg_max, scales, compiled=compiled)
        return mx, at, prefix_dot(cache.blocks, q).mul_(cache.inv_norm).sub_(cache.neg_max)  # the caches' arithmetic

    mx, at, full = streamed_and_full(theta)
    assert torch.equal(mx, full.amax(dim=-1)) and torch.equal(at, full[scales, torch.arange(3)])  # bit for bit
    # Independent: per scale, phi_d normalised, cosine with the text minus the largest with a negative.
    for s, d in enumerate(supervised_dims(12, step)):
        phi = normalize_features(theta[:, :d].double() @ W[:, :d].double().T)
        margin = phi @ texts.double().T - (phi @ negs.double().T).amax(-1, keepdim=True)  # [P, Q]
        torch.testing.assert_close(mx[s].double(), margin.amax(0), rtol=0, atol=1e-5)
        torch.testing.assert_close(at[scales == s].double(), margin.T[scales == s], rtol=0, atol=1e-5)
    # Enough points for two threads.
    big = torch.randn(140_000, 12, generator=g)
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        mx, at, full = streamed_and_full(big)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(mx, full.amax(dim=-1)) and torch.equal(at, full[scales, torch.arange(3)])
    # A NaN feature makes the maxima NaN, as torch.amax does, and only its own margins.
    theta[7, 4] = float("nan")
    mx, at, _ = streamed_and_full(theta)
    assert bool(mx.isnan().all()) and at.isnan().nonzero()[:, 1].unique().tolist() == [7]


def test_selection_ties_where_the_sigmoid_rounds_to_one():
    """Margins that differ but whose relevancy rounds to 1.0 in float32 tie: the first scale is
    chosen, as on the full relevancy tensor (a choice by largest margin would take scale 1)."""
    e = torch.eye(4)
    W = torch.stack([e[0] + 0.3 * e[1], -0.3 * e[1], 0.5 * e[2]], dim=1)  # [E=4, D=3]
    theta = torch.tensor([[1.0, 1.0, 0.0], [-1.0, 0.0, 1.0], [0.2, -1.0, 0.5]])  # Gaussian 0: phi = e0 at d >= 2
    negs = _unit(torch.stack([-e[0] + 0.1 * e[1], -e[0] - 0.1 * e[1], -e[0] + 0.1 * e[2], -e[0] + 0.1 * e[3]]))
    text = e[:1]
    cache = build_prefix_cache(theta, W, negs, 1)
    margins = prefix_margin_max(*cache.terms(text), cache.inv_norm, cache.neg_max)[:, 0]
    assert margins[1] > margins[0] > 1.8  # relevancy sigmoid(10 m) is 1.0 in float32 for both
    ref = torch.stack([_relevancy_literal(theta[:, :d] @ W[:, :d].T, text, negs)[:, 0] for d in (1, 2, 3)])
    assert bool((ref.amax(-1) == 1.0).all())
    chosen, scores, rel = select_scale(cache, text)
    assert chosen.tolist() == [0] and scores.tolist() == [[1.0, 1.0, 1.0]]
    torch.testing.assert_close(rel[0], ref[0], rtol=0, atol=1e-6)
    _assert_same_as_full(chosen, scores, rel, cache.relevancy(text))


# ------------------------------------------------------------------------------ engine (real
# rasterizer and field, a tiny scene, a deterministic stand-in text encoder)
class HashEncoder:
    """Deterministic unit embeddings per text (a stand-in: these tests check plumbing and maths,
    not language understanding)."""

    description = "test hash encoder (random unit vector per text)"

    def __init__(self, dim: int = 16):
        self.dim = dim

    def encode_text(self, texts):
        import zlib

        out = []
        for t in texts:
            g = torch.Generator().manual_seed(zlib.crc32(t.encode()))
            out.append(torch.randn(self.dim, generator=g))
        return torch.nn.functional.normalize(torch.stack(out), dim=-1)


E_TEST = 16


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    from n2f2.data import load_scene
    from n2f2.data.synthetic import generate_demo_scene
    from n2f2.field import FieldConfig, NestedField, bbox_from_points, save_field
    from n2f2.gaussians import init_from_points, write_ply

    root = tmp_path_factory.mktemp("query")
    scene_dir = generate_demo_scene(root / "scene", num_views=2, width=32, height=24, supersample=1,
                                    num_points=400, labelled_views=[0], show_progress=False)
    scene = load_scene(scene_dir)
    g = init_from_points(scene.points, scene.point_colors, sh_degree=1)
    with torch.no_grad():
        g.opacity_logits.fill_(2.0)  # opaque enough for visible renders
        g.log_scales.add_(0.7)
    torch.manual_seed(0)
    field = NestedField(FieldConfig(backbone="mlp", dim=12, hidden=16, pe_frequencies=2, step_size=1),
                        E_TEST, *bbox_from_points(scene.points))
    with torch.no_grad():
        field.W.copy_(torch.randn(E_TEST, 12) / 3.0)
    run = root / "run"
    save_field(run / "field.pt", field, {"encoder_spec": {"name": "captions"}, "scene": str(scene_dir)})
    write_ply(run / "gaussians.ply", g)
    return run


@pytest.fixture(scope="module")
def engine(run_dir):
    from n2f2.query import QueryConfig, QueryEngine

    # The paper's test-time rendering (MLP per Gaussian), which the slow paths below rebuild.
    return QueryEngine.from_run(run_dir, encoder=HashEncoder(E_TEST), config=QueryConfig(selection="max", render="gaussians"))


def test_engine_composite_fast_path_equals_rendered_composite_embedding(engine):
    from n2f2.render import rasterize

    texts = ["lid of the teapot", "red mug", "bag of cookies"]
    view = engine.render_view(0, modes=["composite", "explicit"], rgb=False)
    fast = engine.query(view, texts, "composite").relevancy  # [Q, H, W]
    # Slow path: per-Gaussian composite embedding W Theta~ (E channels), rendered, then scored.
    g = engine.gaussians
    comp = engine.theta_tilde @ engine.W.T
    rendered = rasterize(g.means, g.normalized_quats, g.scales, g.opacities, comp, view.camera).features
    slow = relevancy(rendered.double(), engine.encode(texts).double(),
                     engine.encode(list(engine.config.negatives)).double())
    torch.testing.assert_close(fast.double(), slow.permute(2, 0, 1), rtol=0, atol=1e-5)
    assert fast.shape == (3, view.height, view.width)


def test_engine_explicit_picks_best_scale_of_slow_maps(engine):
    from n2f2.render import rasterize

    texts = ["teapot", "spout"]
    view = engine.render_view(1, modes=["explicit"], rgb=False)
    res = engine.query(view, texts, "explicit")
    g = engine.gaussians
    negs = engine.encode(list(engine.config.negatives))
    slow = []
    for d in engine.scale_dims:  # render phi_d = W[:, :d] Theta[:d] per scale, score it
        phi = engine.theta[:, :d] @ engine.W[:, :d].T
        r = rasterize(g.means, g.normalized_quats, g.scales, g.opacities, phi, view.camera).features
        slow.append(relevancy(r, engine.encode(texts), negs))  # [H, W, Q]
    slow = torch.stack(slow)  # [S, H, W, Q]
    for q in range(2):
        best = int(slow[..., q].flatten(1).amax(1).argmax())
        assert res.chosen[q] == best
        torch.testing.assert_close(res.relevancy[q], slow[best, ..., q], rtol=0, atol=1e-5)
    # LangSplat's choice: highest maximum of the protocol's R' = 0.5 (box(R) + R).
    from n2f2.eval.protocol import smoothed_relevancy

    engine.config.selection, engine.config.box_size = "smoothed", 5
    try:
        res = engine.query(view, texts, "explicit")
    finally:
        engine.config.selection, engine.config.box_size = "max", None
    for q in range(2):
        sm = smoothed_relevancy(slow[..., q].detach().numpy(), 5)
        assert res.chosen[q] == int(sm.reshape(len(sm), -1).max(1).argmax())


def test_engine_oracle_uses_scorer(engine):
    view = engine.render_view(0, modes=["oracle"], rgb=False)
    S = len(engine.scale_dims)
    # A scorer that prefers scale 4 for query 0 and the last scale for query 1.
    want = [4, S - 1]
    res = engine.query(view, ["a", "b"], "oracle", scorer=lambda maps, qi: -np.abs(np.arange(S) - want[qi]))
    assert res.chosen == want
    explicit = engine.query(view, ["a", "b"], "explicit")  # same cache kind
    all_maps = view.caches["prefix"].relevancy(engine.encode(["a", "b"])).view(S, 2, view.height, view.width)
    torch.testing.assert_close(res.relevancy[1], all_maps[S - 1, 1])
    assert explicit.scale_scores.shape == (2, S)


def test_query_gaussians_equals_direct(engine):
    texts = ["teapot", "table"]
    res = engine.query_gaussians(texts)
    direct = relevancy(engine.theta_tilde @ engine.W.T, engine.encode(texts),
                       engine.encode(list(engine.config.negatives)))
    torch.testing.assert_close(res.relevancy, direct.T, rtol=0, atol=1e-6)


@pytest.fixture(scope="module")
def trained_engine(trained_run):
    from n2f2.query import QueryEngine

    return QueryEngine.from_run(trained_run.run_dir)


def _trained_texts(trained_run):
    return [trained_run.part_query, "teapot", "red mug", "wooden table"]


def test_query_gaussians_explicit_equals_per_scale_reference(trained_engine, trained_run):
    eng = trained_engine
    texts = _trained_texts(trained_run)
    res = eng.query_gaussians(texts, "explicit")
    emb, negs = eng.encode(texts), eng.encode(list(eng.config.negatives))
    ref = _explicit_reference(eng.theta, eng.W, emb, negs, eng.scale_dims)  # [S, Q, N]
    ref_scores = ref.amax(dim=-1).T
    _assert_choice(res.chosen, ref_scores)
    assert res.chosen_labels == [f"d={eng.scale_dims[c]}" for c in res.chosen]
    torch.testing.assert_close(res.scale_scores.double(), ref_scores, rtol=0, atol=1e-5)
    for q, c in enumerate(res.chosen):
        torch.testing.assert_close(res.relevancy[q].double(), ref[c, q], rtol=0, atol=1e-5)
    full = eng.gaussian_cache("explicit").relevancy(emb)  # the [S, Q, N] tensor 2D views use
    _assert_same_as_full(torch.tensor(res.chosen), res.scale_scores, res.relevancy, full)


@pytest.mark.parametrize("zero_from", [1, 12])
def test_explicit_ties_pick_the_first_scale(trained_engine, trained_run, zero_from):
    """With theta's dimensions from ``zero_from`` on set to 0, every scale from ``d = zero_from``
    on is the same feature: their scores tie exactly and the first of them is the one chosen
    where they hold the maximum (all queries when ``zero_from = 1``)."""
    eng = trained_engine
    assert eng.step == 1
    texts = _trained_texts(trained_run)
    theta = eng.theta.clone()
    theta[:, zero_from:] = 0.0
    emb, negs = eng.encode(texts), eng.encode(list(eng.config.negatives))
    cache = build_prefix_cache(theta, eng.W, negs, eng.step)  # what gaussian_cache("explicit") builds
    chosen, scores, rel = select_scale(cache, emb)
    ref = _explicit_reference(theta, eng.W, emb, negs, eng.scale_dims)
    ref_scores = ref.amax(dim=-1).T
    tied = slice(zero_from - 1, None)
    assert bool((ref_scores[:, tied] == ref_scores[:, zero_from - 1:zero_from]).all())
    assert bool((scores[:, tied] == scores[:, zero_from - 1:zero_from]).all())
    _assert_choice(chosen.tolist(), ref_scores)
    if zero_from == 1:
        assert chosen.tolist() == [0] * len(texts)
    for q, c in enumerate(chosen.tolist()):
        torch.testing.assert_close(rel[q].double(), ref[c, q], rtol=0, atol=1e-5)
    _assert_same_as_full(chosen, scores, rel, cache.relevancy(emb))


def test_selection_ply_loads_back_and_renders(engine, tmp_path):
    from n2f2.gaussians import read_ply
    from n2f2.render import render_rgb

    rel = engine.query_gaussians(["teapot"]).relevancy[0]
    mask = rel >= rel.median()
    n = engine.export_selection(mask, tmp_path / "sel.ply")
    assert n == int(mask.sum()) > 0
    back = read_ply(tmp_path / "sel.ply")
    torch.testing.assert_close(back.means, engine.gaussians.means[mask].detach())
    cam = engine.scene.cameras[0]
    with torch.no_grad():
        out = render_rgb(back, cam)
    assert out.alpha.shape[:2] == (cam.height, cam.width) and float(out.alpha.max()) > 0.1
    cover = engine.render_selection(mask, 0)
    none = engine.render_selection(torch.zeros_like(mask), 0)
    everything = engine.render_selection(torch.ones_like(mask), 0)
    assert float(none.abs().max()) == 0.0
    view = engine.render_view(0, rgb=False)
    torch.testing.assert_close(everything, view.alpha)  # all selected = the view's opacity
    assert 0.0 < float(cover.sum()) < float(everything.sum())
    default_sel = engine.select("teapot")  # protocol rule: normalised relevancy > 0.4
    norm = (rel - rel.min()) / (rel.max() - rel.min())
    assert torch.equal(default_sel, 2 * norm - 1 > 0.4)


def test_bad_input(engine, run_dir, tmp_path):
    from n2f2.errors import InputError
    from n2f2.query import QueryEngine

    view = engine.render_view(0, rgb=False)
    with pytest.raises(InputError, match="empty query"):
        engine.query(view, ["  "])
    with pytest.raises(InputError, match="no query"):
        engine.query(view, [])
    with pytest.raises(InputError, match="out of range"):
        engine.render_view(2)
    with pytest.raises(InputError, match="levels"):
        engine.query(view, ["a"], "levels")
    with pytest.raises(InputError, match="no field.pt"):
        QueryEngine.from_run(tmp_path)


def test_cli(run_dir, tmp_path, monkeypatch, capsys):
    import n2f2.segments.encoders as encoders
    from n2f2.cli import main

    monkeypatch.setattr(encoders, "get_encoder", lambda spec, device="cpu": HashEncoder(E_TEST))
    out = tmp_path / "out"
    rc = main(["query", str(run_dir), "lid of the teapot", "red mug", "--views", "0", "1",
               "--out", str(out), "--3d", "--box-size", "scaled", "--quiet"])
    assert rc == 0
    summary = json.loads((out / "query.json").read_text())
    assert summary["encoder"] == HashEncoder.description and summary["mode"] == "composite"
    assert summary["composite"]["weights"] == "unit"  # the default weights, recorded
    rec = summary["views"][1]["queries"][0]
    rel = np.load(out / rec["files"]["relevancy"])
    assert rel.dtype == np.float32 and rel.shape == (24, 32)
    assert rec["relevancy_max"] == pytest.approx(float(rel.max()))
    assert (out / rec["files"]["heatmap"]).is_file() and (out / rec["files"]["mask"]).is_file()
    assert (out / "lid-of-the-teapot_selection.ply").is_file()
    assert (out / rec["selection"]["file"]).is_file()
    # Bad input: one clear line, exit code 2, no traceback.
    for argv, msg in [([str(run_dir), "teapot", "--views", "5"], "out of range"),
                      ([str(run_dir), "", "--views", "0"], "empty query"),
                      ([str(tmp_path), "teapot"], "no field.pt"),
                      # a temperature means Eq. 6: alone it would be silently ignored
                      ([str(run_dir), "teapot", "--views", "0", "--temperature", "0.5"], "--composite-weights eq6")]:
        capsys.readouterr()
        assert main(["query", *argv, "--out", str(tmp_path / "x")]) == 2
        err = capsys.readouterr().err
        assert msg in err and "Traceback" not in err
    eq6 = tmp_path / "eq6"
    assert main(["query", str(run_dir), "teapot", "--views", "0", "--out", str(eq6), "--quiet",
                 "--composite-weights", "eq6", "--temperature", "uniform"]) == 0
    composite = json.loads((eq6 / "query.json").read_text())["composite"]
    assert composite["weights"] == "eq6" and composite["temperature"] == "uniform"


def test_deferred_render_equals_the_mlp_of_the_blended_backbone_per_pixel(run_dir, engine):
    """Deferred test views (the default): each pixel's feature is the MLP of the rasterized
    backbone features, and composite applies Eq. 6-7 to that pixel's own prefix features. Slow
    path: the literal formulas per pixel, from a plain rasterization of the backbone."""
    from n2f2.query import QueryConfig, QueryEngine
    from n2f2.render import rasterize

    deferred = QueryEngine.from_run(run_dir, encoder=HashEncoder(E_TEST),
                                    config=QueryConfig(selection="max", composite_weights="eq6"))
    assert deferred.config.render == "deferred"
    texts = ["lid of the teapot", "red mug", "bag of cookies"]
    view = deferred.render_view(0, modes=["composite", "explicit"], rgb=False)
    g, field = deferred.gaussians, deferred.field
    with torch.no_grad():
        f = field.encode(field.normalize(g.means))  # [N, F] backbone at the centres
        blended = rasterize(g.means, g.normalized_quats, g.scales, g.opacities, f, view.camera).features
        theta = field.decode(blended.reshape(-1, f.shape[1])).double()  # [P, D]
    W = field.W.detach().double()
    D = W.shape[1]
    t, negs = deferred.encode(texts).double(), deferred.encode(list(deferred.config.negatives)).double()
    canon = deferred.encode(list(deferred.config.canonical)).double()
    phi = torch.stack([theta[:, :d] @ W[:, :d].T for d in range(1, D + 1)])  # [D, P, E] prefix features
    gamma = torch.softmax((phi @ canon.T).amax(-1) / deferred.config.temperature, dim=0)  # [D, P] Eq. 6
    composite = (gamma[..., None] * phi).sum(0)  # [P, E]
    want = relevancy(composite, t, negs).T.reshape(3, view.height, view.width)
    got = deferred.query(view, texts, "composite").relevancy
    torch.testing.assert_close(got.double(), want, rtol=0, atol=1e-5)
    # n2f2's default weights: the mean of each pixel's normalised prefix features
    unit = QueryEngine.from_run(run_dir, encoder=HashEncoder(E_TEST), config=QueryConfig(selection="max"))
    mean_unit = (phi / phi.norm(dim=-1, keepdim=True).clamp_min(1e-12)).mean(0)  # [P, E]
    want_unit = relevancy(mean_unit, t, negs).T.reshape(3, view.height, view.width)
    got_unit = unit.query(unit.render_view(0, modes=["composite"], rgb=False), texts, "composite").relevancy
    torch.testing.assert_close(got_unit.double(), want_unit, rtol=0, atol=1e-5)
    # explicit: the chosen scale's relevancy is the relevancy of that prefix feature
    res = deferred.query(view, texts, "explicit")
    for q in range(3):
        d = deferred.scale_dims[res.chosen[q]]
        ref = relevancy(phi[d - 1], t[q : q + 1], negs)[:, 0].reshape(view.height, view.width)
        torch.testing.assert_close(res.relevancy[q].double(), ref, rtol=0, atol=1e-5)
    # and it is not the paper's per-Gaussian rendering (the MLP is not linear)
    paper = engine.query(engine.render_view(0, modes=["composite"], rgb=False), texts, "composite").relevancy
    assert float((paper - got).abs().max()) > 1e-3
    # A view of empty space: no pixel is covered, so no feature and relevancy exactly 0.5, as in
    # the per-Gaussian rendering (not the MLP's output for a zero input).
    from dataclasses import replace as dc_replace

    away = dc_replace(view.camera, t=view.camera.t - np.array([0.0, 0.0, 1e4]))  # everything behind the camera
    for eng in (deferred, engine):
        empty = eng.render_view(away, modes=["composite", "explicit"], rgb=False)
        assert float(empty.alpha.abs().max()) == 0.0
        for mode in ("composite", "explicit"):
            assert torch.equal(eng.query(empty, texts, mode).relevancy, torch.full((3, 24, 32), 0.5))


def test_levels_mode_on_a_levels_field(engine):
    from n2f2.field import FieldConfig, NestedField
    from n2f2.query import QueryConfig, QueryEngine
    from n2f2.render import rasterize

    torch.manual_seed(1)
    field = NestedField(FieldConfig(backbone="mlp", dim=12, hidden=16, pe_frequencies=2, variant="levels"),
                        E_TEST, engine.field.bbox_min.numpy(), engine.field.bbox_max.numpy())
    with torch.no_grad():
        field.W.copy_(torch.randn(E_TEST, 12) / 3.0)
    lv = QueryEngine(field, engine.gaussians, HashEncoder(E_TEST), {"config": field.config.to_dict()},
                     QueryConfig(selection="max", render="gaussians"), scene=engine.scene)
    assert lv.modes() == ("levels", "oracle")
    texts = ["teapot", "lid"]
    view = lv.render_view(0, modes=["levels"], rgb=False)
    res = lv.query(view, texts, "levels")
    g = lv.gaussians
    per_level = field.level_features(lv.theta)  # [N, 3, E]
    negs = lv.encode(list(lv.config.negatives))
    slow = torch.stack([relevancy(rasterize(g.means, g.normalized_quats, g.scales, g.opacities,
                                            per_level[:, level], view.camera).features.detach(),
                                  lv.encode(texts), negs) for level in range(3)])  # [3, H, W, Q]
    for q in range(2):
        best = int(slow[..., q].flatten(1).amax(1).argmax())
        assert res.chosen[q] == best and res.chosen_labels[q] == ("part", "object", "group")[best]
        torch.testing.assert_close(res.relevancy[q], slow[best, ..., q], rtol=0, atol=1e-5)
    from n2f2.errors import InputError

    with pytest.raises(InputError, match="levels"):
        lv.query(view, texts, "composite")
    # 3D on the Gaussians: per query the level with the highest maximum, as explicit mode picks a scale.
    res3 = lv.query_gaussians(texts, "levels")
    ref = torch.stack([_relevancy_literal(per_level[:, level].double(), lv.encode(texts).double(),
                                          negs.double()).T for level in range(3)])  # [3, Q, N]
    _assert_choice(res3.chosen, ref.amax(dim=-1).T)
    for q, c in enumerate(res3.chosen):
        torch.testing.assert_close(res3.relevancy[q].double(), ref[c, q], rtol=0, atol=1e-5)
    full = lv.gaussian_cache("levels").relevancy(lv.encode(texts))
    _assert_same_as_full(torch.tensor(res3.chosen), res3.scale_scores, res3.relevancy, full)
