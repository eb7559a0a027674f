"""``lift``: per-Gaussian features against a plain loop over views, pixels and Gaussians with
blending weights read off the brute-force reference rasterizer; the level rules of a bank; the
lift answered by the query engine in 2D and 3D."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from n2f2.cameras import Camera, look_at
from n2f2.field.lift import bank_level_rule, level_segments, lift_features, load_lift, save_lift
from n2f2.query.lifted import build_lift, lift_engine
from n2f2.field.relevancy import relevancy_from_scores

H, W, E = 10, 12, 5


def _scene():
    cams = []
    for eye in ([0.0, -4.0, 0.6], [1.5, -3.6, 0.2]):
        R, t = look_at(np.array(eye), np.zeros(3))
        cams.append(Camera(14.0, 14.0, W / 2, H / 2, W, H, R=R, t=t))
    return SimpleNamespace(cameras=cams, image_names=["frame_00001", "frame_00002"])


def _gaussians():
    g = torch.Generator().manual_seed(0)
    N = 7
    means = (torch.rand(N, 3, generator=g) - 0.5) * torch.tensor([1.6, 1.0, 1.2])
    quats = torch.randn(N, 4, generator=g)
    scales = 0.15 + 0.25 * torch.rand(N, 3, generator=g)
    opac = 0.4 + 0.5 * torch.rand(N, generator=g)
    return {"means": means, "quats": quats / quats.norm(dim=1, keepdim=True), "scales": scales, "opacities": opac}


class _Bank:
    """A segment bank stand-in: 2 views, 3 layers (part, object, group), random segments."""

    def __init__(self, levels=("part", "object", "group"), seed=1):
        rng = np.random.default_rng(seed)
        self.segmenter_spec = {"name": "ground-truth", "levels": list(levels)} if levels else {"name": "sam"}
        self.embed_dim = E
        self.width, self.height = W, H
        self.sizes = [(H, W), (H, W)]
        self.records = []
        for _ in range(2):
            # part layer with holes (-1), object layer in 3 bands, group layer in 2 halves
            part = rng.integers(-1, 3, size=(H, W))
            obj = 3 + np.repeat(np.arange(3), [4, 4, 4])[None, :].repeat(H, 0)
            group = np.where(np.arange(H)[:, None].repeat(W, 1) < 5, 6, 7)
            layers = np.stack([part, obj, group]).astype(np.int32)
            S = 8
            areas = np.bincount(layers[layers >= 0].ravel(), minlength=S).astype(np.int64)
            valid = areas > 0
            valid[1] = False  # a degenerate segment: no supervision, left out of the lift
            quant = np.array([0.1, 0.2, 0.15, 0.5, 0.45, 0.6, 0.9, 0.8], np.float32)
            self.records.append(SimpleNamespace(layers=layers, embeddings=rng.normal(size=(S, E)).astype(np.float16),
                                                areas=areas, valid=valid, quantized=quant))

    def validate_against(self, scene):
        assert len(scene.cameras) == 2

    def record(self, i):
        return self.records[i]


def _weights(geometry, cam) -> np.ndarray:  # [H * W, N] blending weights, from the reference renderer
    from n2f2.render.reference import rasterize_reference

    N = geometry["means"].shape[0]
    out = rasterize_reference(geometry["means"], geometry["quats"], geometry["scales"], geometry["opacities"],
                              torch.eye(N), cam)  # rendering the identity: channel g = w_{p,g}
    return out.features.reshape(-1, N).detach().double().numpy()


def test_lift_equals_weighted_average_loop():
    scene, geometry, bank = _scene(), _gaussians(), _Bank()
    lift = build_lift(geometry, scene, bank, [0, 1])
    N = geometry["means"].shape[0]
    num = np.zeros((N, 3, E))
    den = np.zeros((N, 3))
    for v in (0, 1):
        w = _weights(geometry, scene.cameras[v])
        rec = bank.record(v)
        emb = rec.embeddings.astype(np.float64)
        for p in range(H * W):
            r, c = divmod(p, W)
            for level in range(3):
                s = int(rec.layers[level, r, c])
                if s < 0 or not rec.valid[s]:
                    continue
                for g in range(N):
                    num[g, level] += w[p, g] * emb[s]
                    den[g, level] += w[p, g]
    assert (den > 0).sum() > 10  # most Gaussians are seen at most levels
    avg = np.where(den[..., None] > 0, num / np.maximum(den, 1e-300)[..., None], 0.0)
    norm = np.linalg.norm(avg, axis=-1, keepdims=True)
    want = np.where(norm > 1e-12, avg / np.maximum(norm, 1e-300), 0.0)
    np.testing.assert_allclose(lift.features.numpy(), want, atol=2e-5)
    np.testing.assert_allclose(lift.weights.numpy(), den, rtol=1e-4, atol=1e-6)
    assert lift.rule == "layers" and lift.features.shape == (N, 3, E)


def test_lift_without_the_compiled_kernel_is_the_same(monkeypatch):
    """The torch path (no numba, or too many bins for the dense buffer) sums the same triples."""
    import n2f2.field.lift as lift_mod
    from n2f2.train.blend import build_blend_cache

    scene, geometry, bank = _scene(), _gaussians(), _Bank()
    cache = build_blend_cache(geometry, scene.cameras)
    a = lift_features(cache, [0, 1], bank, geometry["means"].shape[0])
    monkeypatch.setattr(lift_mod, "_DENSE_BINS", 0)
    b = lift_features(cache, [0, 1], bank, geometry["means"].shape[0])
    torch.testing.assert_close(a.features, b.features, atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(a.weights, b.weights)


def test_lift_from_a_given_cache_checks_it_and_round_trips(tmp_path):
    from n2f2.train.blend import build_blend_cache

    scene, geometry, bank = _scene(), _gaussians(), _Bank()
    cache = build_blend_cache(geometry, scene.cameras)
    a = lift_features(cache, [0, 1], bank, geometry["means"].shape[0])
    b = build_lift(geometry, scene, bank, [0, 1])
    torch.testing.assert_close(a.features, b.features)
    assert set(b.seconds) == {"blend", "lift", "total"}
    with pytest.raises(ValueError, match="blend cache"):
        lift_features(cache, [1], bank, geometry["means"].shape[0])
    save_lift(tmp_path / "lift.pt", a)
    c = load_lift(tmp_path / "lift.pt", num_gaussians=geometry["means"].shape[0])
    torch.testing.assert_close(c.features, a.features, atol=1e-3, rtol=0)  # stored as float16
    assert c.views == [0, 1] and c.rule == "layers"


def test_level_rules():
    assert bank_level_rule(_Bank()) == ("layers", (0, 1, 2))
    assert bank_level_rule(SimpleNamespace(segmenter_spec={"name": "langsplat", "levels": ["default", "s", "m", "l"]})) \
        == ("layers", (1, 2, 3))
    bank = _Bank(levels=None)
    assert bank_level_rule(bank) == ("terciles", None)
    rec = bank.record(0)
    ids = level_segments(rec, ("terciles", None))
    # terciles of the quantized scale: segments 0, 2 (s < 1/3) part; 3, 4, 5 object; 6, 7 group.
    # Each pixel takes its smallest covering segment of the tercile (segment 1 is invalid).
    for r in range(H):
        for c in range(W):
            cover = [int(rec.layers[k, r, c]) for k in range(3) if rec.layers[k, r, c] >= 0]
            for level, members in enumerate(([0, 2], [3, 4, 5], [6, 7])):
                cands = [s for s in cover if s in members and rec.valid[s]]
                want = min(cands, key=lambda s: rec.areas[s]) if cands else -1
                assert ids[level, r, c] == want


def test_lift_engine_levels_and_3d():
    """The lift answers like a 3-level field: per Gaussian, relevancy of each level's feature
    with the one relevancy formula, and the level with the highest maximum chosen."""
    scene, geometry, bank = _scene(), _gaussians(), _Bank()
    lift = build_lift(geometry, scene, bank, [0, 1])
    rng = np.random.default_rng(5)
    vocab = {t: rng.normal(size=E) for t in ["a", "b", "neg1", "neg2"]}
    encoder = SimpleNamespace(encode_text=lambda texts: np.stack([vocab[t] for t in texts]), description="test")
    from n2f2.query.engine import QueryConfig

    gauss = SimpleNamespace(means=geometry["means"], normalized_quats=geometry["quats"], scales=geometry["scales"],
                            opacities=geometry["opacities"])
    engine = lift_engine(lift, gauss, encoder, {"encoder_spec": {"name": "test"}},
                         QueryConfig(negatives=("neg1", "neg2")), scene=scene)
    assert engine.modes() == ("levels", "oracle")
    res = engine.query_gaussians(["a", "b"], mode="levels")
    t = torch.nn.functional.normalize(torch.tensor(np.stack([vocab["a"], vocab["b"]]), dtype=torch.float32), dim=-1)
    n = torch.nn.functional.normalize(torch.tensor(np.stack([vocab["neg1"], vocab["neg2"]]), dtype=torch.float32), dim=-1)
    f = lift.features  # [N, 3, E] unit (or 0)
    per_level = relevancy_from_scores(torch.einsum("nle,qe->lqn", f, t),
                                      torch.einsum("nle,ce->lnc", f, n).amax(-1)[:, None, :])  # [3, Q, N]
    chosen = per_level.amax(-1).argmax(0)  # [Q]
    assert res.chosen == chosen.tolist()
    torch.testing.assert_close(res.relevancy, per_level[chosen, torch.arange(2)], atol=1e-5, rtol=1e-5)
    view = engine.render_view(0, modes=["levels"], rgb=False)
    out = engine.query(view, ["a"], mode="levels")
    assert out.relevancy.shape == (1, H, W) and torch.isfinite(out.relevancy).all()
