"""RGB fitting of Gaussians: losses, optimiser, densification, NaN guard, checkpoints and resume."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from n2f2.cameras import Camera, look_at
from n2f2.cli import main as cli_main
from n2f2.data.scene import Scene
from n2f2.gaussians import Gaussians, read_ply
from n2f2.gaussians import fit as fit_mod
from n2f2.gaussians.fit import fit_gaussians
from n2f2.gaussians.fit_config import FitConfig, split_views
from n2f2.gaussians.optim import (
    DensifyStats, GaussianAdam, _gaussian_1d, blur_reference, densify_and_prune, photometric_loss, reset_opacity,
    ssim,
)
from n2f2.io import write_json, write_png
from n2f2.render import render_rgb

W, H, N_VIEWS = 32, 24, 8


def _gt_gaussians(n: int = 60, seed: int = 0) -> Gaussians:
    rng = np.random.default_rng(seed)
    t = lambda a: torch.tensor(a, dtype=torch.float32)  # noqa: E731
    return Gaussians(t(rng.uniform(-1, 1, (n, 3))), t(rng.normal(size=(n, 4))),
                     t(np.log(rng.uniform(0.1, 0.3, (n, 3)))), torch.full((n,), 3.0),
                     t(rng.normal(size=(n, 1, 3))))


def _cameras() -> list[Camera]:
    cams = []
    for i in range(N_VIEWS):
        a = 2 * np.pi * i / N_VIEWS
        R, t = look_at(np.array([4 * np.cos(a), 4 * np.sin(a), 1.5]), np.zeros(3))
        cams.append(Camera(1.2 * W, 1.2 * W, W / 2, H / 2, W, H, R=R, t=t))
    return cams


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory) -> Scene:
    """A tiny scene whose images are renders of known Gaussians, also saved as transforms.json."""
    root = tmp_path_factory.mktemp("tiny_scene")
    gt = _gt_gaussians()
    cams = _cameras()
    paths, frames = [], []
    for i, cam in enumerate(cams):
        with torch.no_grad():
            img = render_rgb(gt, cam).features.clamp(0, 1).numpy()
        path = root / "images" / f"frame_{i + 1:05d}.png"
        write_png(path, img)
        paths.append(path)
        frames.append({"file_path": f"images/{path.name}", "transform_matrix": cam.opengl_c2w().tolist()})
    rng = np.random.default_rng(1)
    points = gt.means.detach().double().numpy() + rng.normal(scale=0.05, size=(gt.num, 3))
    colors = (rng.uniform(0, 1, (gt.num, 3)) * 255).astype(np.uint8)
    # nerfstudio's sparse points: an ascii PLY with x y z red green blue
    rows = "".join(f"{p[0]:.9g} {p[1]:.9g} {p[2]:.9g} {c[0]} {c[1]} {c[2]}\n" for p, c in zip(points, colors))
    (root / "points.ply").write_text(
        f"ply\nformat ascii 1.0\nelement vertex {len(points)}\nproperty double x\nproperty double y\n"
        "property double z\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n" + rows)
    c = cams[0]
    write_json(root / "transforms.json", {"fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": W, "h": H,
                                          "frames": frames, "ply_file_path": "points.ply"})
    return Scene(root=root, cameras=cams, image_paths=paths, points=points, point_colors=colors)


def _tiny_config(**kw) -> FitConfig:
    base = replace(FitConfig.cpu(), steps=30, densify_from=10, densify_every=10, densify_until=25,
                   opacity_reset_every=1000, sh_degree_interval=10, sh_degree=1, checkpoint_every=0,
                   max_gaussians=400, log_every=1)
    return replace(base, **kw)


def _mean_l1(g: Gaussians, scene: Scene, views: list[int]) -> float:
    with torch.no_grad():
        return float(np.mean([(render_rgb(g, scene.cameras[i], background=(0, 0, 0)).features
                               - torch.from_numpy(scene.image(i))).abs().mean() for i in views]))


# ------------------------------------------------------------------------------------ losses
def _ssim_reference(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM from scipy's correlate with zero padding and an 11x11 Gaussian (sigma 1.5)."""
    from scipy.ndimage import correlate

    x = np.arange(11) - 5.0
    g = np.exp(-x ** 2 / (2 * 1.5 ** 2))
    g /= g.sum()
    w = np.outer(g, g)
    f = lambda im: correlate(im, w, mode="constant", cval=0.0)  # noqa: E731
    vals = []
    for c in range(a.shape[2]):
        x1, x2 = a[..., c].astype(np.float64), b[..., c].astype(np.float64)
        m1, m2 = f(x1), f(x2)
        s1, s2, s12 = f(x1 * x1) - m1 ** 2, f(x2 * x2) - m2 ** 2, f(x1 * x2) - m1 * m2
        c1, c2 = 0.01 ** 2, 0.03 ** 2
        vals.append(((2 * m1 * m2 + c1) * (2 * s12 + c2)) / ((m1 ** 2 + m2 ** 2 + c1) * (s1 + s2 + c2)))
    return float(np.mean(vals))


def test_ssim_matches_reference_and_identity():
    rng = np.random.default_rng(0)
    a = rng.uniform(size=(20, 27, 3)).astype(np.float32)
    b = np.clip(a + rng.normal(scale=0.1, size=a.shape), 0, 1).astype(np.float32)
    got = float(ssim(torch.from_numpy(a), torch.from_numpy(b)))
    assert got == pytest.approx(_ssim_reference(a, b), abs=1e-5)
    assert float(ssim(torch.from_numpy(a), torch.from_numpy(a))) == pytest.approx(1.0, abs=1e-6)
    # the loss is (1 - 0.2) L1 + 0.2 (1 - SSIM)
    loss = float(photometric_loss(torch.from_numpy(a), torch.from_numpy(b), 0.2))
    assert loss == pytest.approx(0.8 * np.abs(a - b).mean() + 0.2 * (1 - _ssim_reference(a, b)), abs=1e-5)


@pytest.mark.parametrize(("dtype", "tol"), [(torch.float64, 1e-12), (torch.float32, 1e-5)])
@pytest.mark.parametrize("shape", [(15, 23, 17), (4, 7, 30)])  # (4, 7, 30): fewer rows than taps
def test_compiled_blur_matches_the_reference_with_gradients(dtype, tol, shape):
    pytest.importorskip("numba")
    from n2f2.gaussians.numba_ssim import blur_numba

    g = torch.Generator().manual_seed(3)
    maps = torch.rand(shape, generator=g, dtype=dtype)
    upstream = torch.randn(shape, generator=g, dtype=dtype)
    # An asymmetric window: the backward must reverse it (the Gaussian's symmetry would hide that).
    for window in (_gaussian_1d(11, 1.5, "cpu", dtype), torch.rand(5, generator=g, dtype=dtype)):
        results = []
        for fn in (blur_reference, blur_numba):
            leaf = maps.clone().requires_grad_(True)
            out = fn(leaf, window)
            results.append((out.detach(), torch.autograd.grad((out * upstream).sum(), leaf)[0]))
        (want, want_grad), (got, got_grad) = results
        assert got.dtype == dtype and got.shape == want.shape
        torch.testing.assert_close(got, want, rtol=tol, atol=tol)
        torch.testing.assert_close(got_grad, want_grad, rtol=tol, atol=tol * float(want_grad.abs().max()))


def test_compiled_blur_hand_worked_and_gradcheck():
    pytest.importorskip("numba")
    from n2f2.gaussians.numba_ssim import blur_numba

    # One 1 in the middle of a 5x5 map, window (1, 2, 3): the output is the outer product of the
    # window reversed (a correlation), zero padded.
    x = torch.zeros(1, 5, 5, dtype=torch.float64)
    x[0, 2, 2] = 1.0
    w = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    want = torch.zeros(5, 5, dtype=torch.float64)
    want[1:4, 1:4] = torch.outer(w.flip(0), w.flip(0))
    torch.testing.assert_close(blur_numba(x, w)[0], want, rtol=0, atol=0)
    # at the border the padding is zero: a 1 in the corner keeps only the window's part inside
    x = torch.zeros(1, 4, 6, dtype=torch.float64)
    x[0, 0, 0] = 1.0
    assert blur_numba(x, w)[0, 0, 0] == 2.0 * 2.0 and blur_numba(x, w)[0, 1, 1] == 1.0 * 1.0
    maps = torch.rand(2, 6, 9, dtype=torch.float64, requires_grad=True)
    window = torch.rand(5, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    assert torch.autograd.gradcheck(lambda m: blur_numba(m, window), (maps,))


# ------------------------------------------------------------------------------------ optimiser
@pytest.mark.parametrize("compiled", [False, True])
def test_gaussian_adam_matches_torch_adam(compiled):
    torch.manual_seed(0)
    x0 = torch.randn(5, 3)
    target = torch.randn(5, 3)
    a = x0.clone().requires_grad_(True)
    b = x0.clone().requires_grad_(True)
    ref = torch.optim.Adam([a], lr=0.01, eps=1e-15)
    ours = GaussianAdam(eps=1e-15, compiled=compiled)
    for _ in range(7):
        for p in (a, b):
            p.grad = None
            ((p - target) ** 3).abs().sum().backward()
        ref.step()
        assert ours.step({"x": b}, {"x": 0.01})
    torch.testing.assert_close(b, a, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("compiled", [False, True])
def test_gaussian_adam_with_a_rate_per_coefficient_matches_torch_adam_groups(compiled):
    # The SH tensor's rates: one for the DC coefficient, one for the rest, as a [1, K, 1] tensor;
    # torch.optim.Adam gets the two slices as separate parameters of two groups.
    g = torch.Generator().manual_seed(4)
    sh0 = torch.randn(300, 4, 3, generator=g)
    target = torch.randn(300, 4, 3, generator=g)
    dc, rest = sh0[:, :1].clone().requires_grad_(True), sh0[:, 1:].clone().requires_grad_(True)
    ref = torch.optim.Adam([{"params": [dc], "lr": 0.02}, {"params": [rest], "lr": 0.001}], eps=1e-15)
    sh = sh0.clone().requires_grad_(True)
    ours = GaussianAdam(eps=1e-15, compiled=compiled)
    rate = torch.tensor([0.02, 0.001, 0.001, 0.001]).reshape(1, 4, 1)
    empty = torch.zeros(0, 3, requires_grad=True)  # a parameter with no rows (all pruned)
    for _ in range(20):
        for p in (dc, rest, sh):
            p.grad = None
        ((torch.cat([dc, rest], 1) - target) ** 3).abs().sum().backward()
        ((sh - target) ** 3).abs().sum().backward()
        empty.grad = torch.zeros(0, 3)
        ref.step()
        assert ours.step({"sh": sh, "empty": empty}, {"sh": rate, "empty": 0.1})
    torch.testing.assert_close(sh.detach(), torch.cat([dc, rest], 1).detach(), rtol=1e-5, atol=1e-6)
    assert not torch.equal(sh.detach(), sh0)


def test_gaussian_adam_rejects_non_finite_update():
    p = torch.zeros(3, requires_grad=True)
    adam = GaussianAdam()
    p.grad = torch.ones(3)
    assert adam.step({"p": p}, {"p": 0.1})
    before = (p.detach().clone(), adam.exp_avg["p"].clone(), adam.step_count["p"])
    p.grad = torch.tensor([1.0, float("nan"), 0.0])
    assert not adam.step({"p": p}, {"p": 0.1})
    assert torch.equal(p.detach(), before[0]) and torch.equal(adam.exp_avg["p"], before[1])
    assert adam.step_count["p"] == before[2]
    # Infinite, or finite but so large that its square overflows float32: refused as well.
    for bad in (float("-inf"), 3e19):
        p.grad = torch.tensor([1.0, bad, 0.0])
        assert not adam.step({"p": p}, {"p": 0.1})
        assert torch.equal(p.detach(), before[0]) and adam.step_count["p"] == before[2]
    p.grad = torch.tensor([1.0, 1e18, 0.0])  # below the limit: taken
    assert adam.step({"p": p}, {"p": 0.1}) and adam.step_count["p"] == before[2] + 1


# ------------------------------------------------------------------------------------ densification
def _hand_gaussians() -> Gaussians:
    # 0: small, high grad -> clone; 1: large, high grad -> split; 2: low grad, kept;
    # 3: transparent -> pruned; 4: low grad, huge -> pruned only when prune_big.
    means = torch.tensor([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [4, 0, 0]])
    log_scales = torch.log(torch.tensor([[0.001] * 3, [0.5, 0.2, 0.1], [0.001] * 3, [0.001] * 3, [5.0] * 3]))
    opac = torch.logit(torch.tensor([0.5, 0.6, 0.7, 0.001, 0.5]))
    quats = torch.tensor([[1.0, 0, 0, 0]] * 5)
    sh = torch.arange(5 * 4 * 3, dtype=torch.float32).reshape(5, 4, 3)
    return Gaussians(means, quats, log_scales, opac, sh)


def _stats(grads: list[float]) -> DensifyStats:
    n = len(grads)
    return DensifyStats(torch.tensor(grads) * 2, torch.full((n,), 2.0), torch.zeros(n))


def _adam_with_row_ids(g: Gaussians) -> GaussianAdam:
    adam = GaussianAdam()
    for name, p in g.params().items():
        ids = torch.arange(1, g.num + 1, dtype=torch.float32).reshape((-1,) + (1,) * (p.ndim - 1))
        adam.exp_avg[name] = ids.expand_as(p).clone()
        adam.exp_avg_sq[name] = ids.expand_as(p).clone()
        adam.step_count[name] = 3
    return adam


def test_densify_clone_split_prune():
    g = _hand_gaussians()
    adam = _adam_with_row_ids(g)
    cfg = replace(FitConfig(), densify_grad_threshold=1e-3, percent_dense=0.01, prune_world_size=0.1)
    extent = 10.0  # clone below 0.1, prune above 1.0 world units
    counts = densify_and_prune(g, adam, _stats([5e-3, 5e-3, 1e-4, 1e-4, 1e-4]), cfg, extent, prune_big=True,
                               generator=torch.Generator().manual_seed(0))
    assert counts == {"cloned": 1, "split": 1, "pruned": 2}
    # survivors: 0, 2, then the clone of 0, then two children of 1
    assert g.num == 5
    m = g.means.detach()
    assert torch.equal(m[0], torch.tensor([0.0, 0, 0])) and torch.equal(m[1], torch.tensor([2.0, 0, 0]))
    assert torch.equal(m[2], torch.tensor([0.0, 0, 0]))
    torch.testing.assert_close(g.scales[3:], torch.tensor([[0.5, 0.2, 0.1]] * 2) / 1.6)
    # children are drawn from N(mean, diag(scale^2)) in the parent's frame: within 6 sigma
    assert torch.all((m[3:] - torch.tensor([1.0, 0, 0])).abs() <= 6 * torch.tensor([0.5, 0.2, 0.1]))
    assert torch.equal(g.sh[3], torch.arange(12, 24, dtype=torch.float32).reshape(4, 3))
    # Adam state follows its rows; new rows start at zero
    assert adam.exp_avg["means"][:, 0].tolist() == [1.0, 3.0, 0.0, 0.0, 0.0]
    assert adam.exp_avg_sq["sh"][:, 0, 0].tolist() == [1.0, 3.0, 0.0, 0.0, 0.0]
    assert all(t.shape[0] == 5 for d in (adam.exp_avg, adam.exp_avg_sq) for t in d.values())


def test_densify_without_prune_big_keeps_huge_gaussian():
    g = _hand_gaussians()
    densify_and_prune(g, _adam_with_row_ids(g), _stats([0.0] * 5), replace(FitConfig(), densify_grad_threshold=1),
                      10.0, prune_big=False, generator=torch.Generator())
    assert g.num == 4 and torch.equal(g.means.detach()[:, 0], torch.tensor([0.0, 1, 2, 4]))


def test_densify_respects_cap_and_keeps_largest_gradients():
    g = _hand_gaussians()
    cfg = replace(FitConfig(), densify_grad_threshold=1e-3, max_gaussians=6)  # room for one more
    counts = densify_and_prune(g, _adam_with_row_ids(g), _stats([5e-3, 9e-3, 1e-4, 1e-4, 1e-4]), cfg, 10.0,
                               prune_big=False, generator=torch.Generator())
    assert counts["cloned"] == 0 and counts["split"] == 1  # Gaussian 1 has the larger gradient


def test_densify_splits_large_on_screen_gaussians():
    g = _hand_gaussians()
    stats = _stats([0.0] * 5)
    stats.max_radii = torch.tensor([0.2, 0.0, 0.01, 0.0, 0.0])  # Gaussian 0 covers 20% of the image
    cfg = replace(FitConfig(), densify_grad_threshold=1.0, split_screen_size=0.05)
    counts = densify_and_prune(g, _adam_with_row_ids(g), stats, cfg, 10.0, prune_big=False,
                               generator=torch.Generator().manual_seed(0))
    assert counts == {"cloned": 0, "split": 1, "pruned": 1}  # split although small in world units
    torch.testing.assert_close(g.scales[-2:], torch.full((2, 3), 0.001 / 1.6))


def test_reset_opacity():
    g = _hand_gaussians()
    adam = _adam_with_row_ids(g)
    reset_opacity(g, adam, 0.01)
    torch.testing.assert_close(g.opacities, torch.tensor([0.01, 0.01, 0.01, 0.001, 0.01]))
    assert torch.all(adam.exp_avg["opacity_logits"] == 0) and torch.all(adam.exp_avg["means"] > 0)


def test_densify_stats_ndc_scaling():
    s = DensifyStats.zeros(3, "cpu")
    s.add(torch.tensor([[1.0, 0.0], [0.0, 2.0], [5.0, 5.0]]), torch.tensor([3, 4, 0], dtype=torch.int32), 20, 10)
    torch.testing.assert_close(s.grad_accum, torch.tensor([10.0, 10.0, 0.0]))  # x * W/2, y * H/2
    assert s.count.tolist() == [1.0, 1.0, 0.0] and s.max_radii.tolist() == pytest.approx([3 / 20, 4 / 20, 0.0])
    # A second view: Gaussian 1 hidden (its gradient NaN, ignored), a smaller radius keeps the maximum.
    s.add(torch.tensor([[0.5, 0.0], [float("nan"), 1.0], [0.0, 0.1]]), torch.tensor([1, 0, 2], dtype=torch.int32), 20, 10)
    torch.testing.assert_close(s.grad_accum, torch.tensor([15.0, 10.0, 0.5]))
    assert s.count.tolist() == [2.0, 1.0, 1.0] and s.max_radii.tolist() == pytest.approx([3 / 20, 4 / 20, 2 / 20])


def test_split_views(tiny_scene, tmp_path):
    assert split_views(tiny_scene, 8) == ([1, 2, 3, 4, 5, 6, 7], [0])
    assert split_views(tiny_scene, 0) == (list(range(8)), [])
    scene = replace(tiny_scene, root=tmp_path)
    (tmp_path / "scene.json").write_text(json.dumps({"test_views": [2, 5]}))
    assert split_views(scene, 8) == ([0, 1, 3, 4, 6, 7], [2, 5])
    (tmp_path / "scene.json").write_text(json.dumps({"test_views": [9]}))
    with pytest.raises(Exception, match="test_views"):
        split_views(scene, 8)


# ------------------------------------------------------------------------------------ fitting
def test_small_fit_lowers_loss(tiny_scene, tmp_path):
    cfg = _tiny_config()
    train, _ = split_views(tiny_scene, cfg.test_every)
    init = fit_mod.initial_gaussians(tiny_scene, cfg, None)
    before = _mean_l1(init, tiny_scene, train)
    report = fit_gaussians(tiny_scene, cfg, tmp_path, progress=False)
    g = read_ply(tmp_path / "gaussians.ply")
    after = _mean_l1(g, tiny_scene, train)
    assert after < 0.9 * before
    data = json.loads((tmp_path / "fit_report.json").read_text())
    assert data["steps"] == 30 and data["num_gaussians"] == g.num == report.num_gaussians
    assert data["skipped_steps"] == 0 and data["test_views"] == [0]
    assert data["loss_curve"][0][0] == 1 and data["loss_curve"][-1][0] == 30
    assert data["train_psnr"] > 0 and data["test_psnr"] > 0
    assert g.num != init.num  # densification ran (clone/split/prune)


def test_depth_spread_of_two_stacked_gaussians():
    """Two wide Gaussians on the optical axis at z1 < z2: at the centre pixel the blended
    weights are alpha1 and alpha2 (1 - alpha1), and the spread is sum w z^2 - (sum w z)^2 / sum w."""
    cam = Camera(20.0, 20.0, 8.0, 8.0, 16, 16, R=np.eye(3), t=np.zeros(3))
    z = torch.tensor([2.0, 3.0])
    o = torch.tensor([0.6, 0.9])
    g = Gaussians(torch.stack([torch.zeros(2), torch.zeros(2), z], 1), torch.tensor([[1.0, 0, 0, 0]] * 2),
                  torch.log(torch.tensor([[5.0, 5.0, 0.01]] * 2)), torch.logit(o), torch.zeros(2, 1, 3))
    extent = 2.0
    _, spread = fit_mod._render_with_depth_spread(g, cam, FitConfig(), extent)
    w = torch.stack([o[0], o[1] * (1 - o[0])])  # alphas at the centre are the opacities (to ~1e-5)
    zs = z / extent
    expected = (w * zs * zs).sum() - (w * zs).sum() ** 2 / w.sum()
    assert float(spread[8, 8].detach()) == pytest.approx(float(expected), rel=1e-3)
    # One Gaussian alone: nothing to spread.
    _, single = fit_mod._render_with_depth_spread(g.subset(torch.tensor([0])), cam, FitConfig(), extent)
    assert float(single.detach().abs().max()) < 1e-5


def test_fit_with_depth_spread_runs_and_lowers_loss(tiny_scene, tmp_path):
    cfg = replace(_tiny_config(), depth_spread_weight=1.0)
    train, _ = split_views(tiny_scene, cfg.test_every)
    before = _mean_l1(fit_mod.initial_gaussians(tiny_scene, cfg, None), tiny_scene, train)
    report = fit_gaussians(tiny_scene, cfg, tmp_path, progress=False)
    assert report.skipped_steps == 0
    assert _mean_l1(read_ply(tmp_path / "gaussians.ply"), tiny_scene, train) < 0.9 * before


@pytest.mark.parametrize("every, resets, prune_big", [(10, [10, 20], True), (0, [], False)])
def test_opacity_reset_schedule_and_off_switch(tiny_scene, tmp_path, monkeypatch, every, resets, prune_big):
    """Resets happen every N steps until densification ends; 0 turns them off, and then large
    Gaussians are never pruned (3DGS prunes them only after the first reset)."""
    seen, big = [], []
    real_reset, real_densify = fit_mod.reset_opacity, fit_mod.densify_and_prune
    step = {"n": 0}

    def counting_reset(g, adam):
        seen.append(step["n"])
        return real_reset(g, adam)

    def recording_densify(*args, prune_big, **kw):
        big.append(prune_big)
        return real_densify(*args, prune_big=prune_big, **kw)

    real_loss = fit_mod.photometric_loss

    def counting_loss(*args, **kw):
        step["n"] += 1
        return real_loss(*args, **kw)

    monkeypatch.setattr(fit_mod, "reset_opacity", counting_reset)
    monkeypatch.setattr(fit_mod, "densify_and_prune", recording_densify)
    monkeypatch.setattr(fit_mod, "photometric_loss", counting_loss)
    fit_gaussians(tiny_scene, _tiny_config(opacity_reset_every=every), tmp_path, progress=False)
    assert seen == resets  # densify_until = 25: no reset at 30
    assert big == [prune_big]  # densification runs once, at step 20 (after the reset at 10)


def test_nan_step_is_skipped_and_not_checkpointed(tiny_scene, tmp_path, monkeypatch):
    calls = {"n": 0}
    real = fit_mod.photometric_loss

    def flaky(render, target, lam):
        calls["n"] += 1
        loss = real(render, target, lam)
        return loss * float("nan") if calls["n"] in (3, 4, 7) else loss

    monkeypatch.setattr(fit_mod, "photometric_loss", flaky)
    report = fit_gaussians(tiny_scene, _tiny_config(steps=12, checkpoint_every=4), tmp_path, progress=False)
    assert report.skipped_steps == 3
    ck = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert ck["step"] == 12 and ck["skipped"] == 3
    assert all(torch.isfinite(t).all() for t in ck["params"].values())
    assert read_ply(tmp_path / "gaussians.ply").finite()


def test_non_finite_state_is_never_checkpointed(tiny_scene, tmp_path, monkeypatch):
    monkeypatch.setattr(fit_mod, "_state_finite", lambda g, adam: False)
    fit_gaussians(tiny_scene, _tiny_config(steps=4, checkpoint_every=2), tmp_path, progress=False)
    assert not (tmp_path / "checkpoint.pt").exists()


# One thread: the CPU rasterizer's backward is only bit-reproducible single-threaded (its
# multi-threaded reductions may sum in a different order), and the comparison below is exact.
_CHILD = """
import sys, torch
torch.set_num_threads(1)
from n2f2.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _cli_args(scene_root: Path, out: Path, steps: int) -> list[str]:
    return ["fit-gaussians", str(scene_root), "--out", str(out), "--steps", str(steps), "--checkpoint-every", "3",
            "--max-gaussians", "300", "--quiet", "--seed", "3"]


def _run_cli(args: list[str]) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", _CHILD] + args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)


def _finish(proc: subprocess.Popen) -> None:
    _, err = proc.communicate()
    assert proc.returncode == 0, err


def test_kill_and_resume_matches_uninterrupted_run(tiny_scene, tmp_path):
    steps = 40
    # An uninterrupted run through the CLI.
    full = tmp_path / "full"
    _finish(_run_cli(_cli_args(tiny_scene.root, full, steps)))

    # The same run, killed (SIGKILL) once a checkpoint exists.
    cut = tmp_path / "cut"
    proc = _run_cli(_cli_args(tiny_scene.root, cut, steps))
    deadline = time.time() + 50
    while not (cut / "checkpoint.pt").exists() and proc.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    ck = torch.load(cut / "checkpoint.pt", weights_only=True)
    killed_at = ck["step"]
    assert killed_at % 3 == 0 and 3 <= killed_at < steps
    assert not (cut / "gaussians.ply").exists()  # the killed run never got to write its result

    _finish(_run_cli(_cli_args(tiny_scene.root, cut, steps) + ["--resume"]))
    report = json.loads((cut / "fit_report.json").read_text())
    assert report["resumed_from"] == killed_at and report["steps"] == steps
    a, b = read_ply(full / "gaussians.ply"), read_ply(cut / "gaussians.ply")
    assert a.num == b.num
    for name in ["means", "quats", "log_scales", "opacity_logits", "sh"]:
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    full_report = json.loads((full / "fit_report.json").read_text())
    assert report["loss_curve"] == full_report["loss_curve"]


def test_resume_with_bad_checkpoint_is_a_clear_error(tiny_scene, tmp_path, capsys):
    (tmp_path / "checkpoint.pt").write_bytes(b"not a checkpoint")
    assert cli_main(_cli_args(tiny_scene.root, tmp_path, 5) + ["--resume"]) == 2
    assert "checkpoint.pt" in capsys.readouterr().err


@pytest.mark.parametrize("value", ["-1", "nan"])
def test_negative_or_nan_depth_spread_is_a_clear_error(tiny_scene, tmp_path, capsys, value):
    with pytest.raises(SystemExit) as e:  # refused by the option's type, while parsing
        cli_main(_cli_args(tiny_scene.root, tmp_path / "out", 5) + ["--depth-spread", value])
    assert e.value.code == 2
    assert "--depth-spread must be a finite number >= 0" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
