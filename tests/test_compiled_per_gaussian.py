"""The compiled per-Gaussian steps of the CPU renderer against their PyTorch references: the
projection (n2f2.render.numba_project), the tile binning (n2f2.render.numba_bins) and the
spherical-harmonics colours (n2f2.render.numba_sh)."""

from __future__ import annotations

import math

import pytest
import torch

from n2f2.cameras import Camera
from n2f2.render.numba_bins import bin_gaussians_numba
from n2f2.render.numba_pairs import pair_coefficients_numba
from n2f2.render.numba_project import project_gaussians_numba
from n2f2.render.numba_sh import sh_colors
from n2f2.render.sh import eval_sh, eval_sh_torch, num_sh_bases
from n2f2.render.torch_backend import bin_gaussians, pair_coefficients, project_gaussians

pytest.importorskip("numba")

CAMERA = Camera(fx=120.0, fy=110.0, cx=80.0, cy=60.0, width=160, height=120)


def _viewmat(dtype: torch.dtype) -> torch.Tensor:  # a turned, shifted camera
    th = 0.3
    vm = torch.eye(4, dtype=dtype)
    vm[:3, :3] = torch.tensor(
        [[math.cos(th), 0.0, math.sin(th)], [0.0, 1.0, 0.0], [-math.sin(th), 0.0, math.cos(th)]], dtype=dtype
    )
    vm[:3, 3] = torch.tensor([0.1, -0.2, 0.3], dtype=dtype)
    return vm


def _gaussians(n: int, dtype: torch.dtype, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=dtype) * torch.tensor([2.0, 1.5, 1.0], dtype=dtype)
    means[:, 2] += 2.5
    means[:5, 2] = -1.0  # behind the camera: culled
    means[5:10, 0] = 50.0  # far outside the image: the Jacobian's clamp is active
    quats = torch.randn(n, 4, generator=g, dtype=dtype)  # not normalised
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * 0.2 + 0.01
    opacities = torch.rand(n, generator=g, dtype=dtype)
    opacities[10:13] = 1e-4  # below alpha_min: no extent
    return means, quats, scales, opacities


def _project(fn, dtype):
    means, quats, scales, opacities = _gaussians(300, dtype)
    K = CAMERA.to_torch(device="cpu", dtype=dtype)["K"]
    params = [t.clone().requires_grad_(True) for t in (means, quats, scales)]
    proj = fn(*params, opacities, _viewmat(dtype), K, CAMERA.width, CAMERA.height)
    g = torch.Generator().manual_seed(1)
    weights = [torch.randn(t.shape, generator=g, dtype=dtype) for t in (proj.means2d, proj.conics, proj.depths)]
    v = proj.valid
    loss = (
        (proj.means2d * weights[0])[v].sum() + (proj.conics * weights[1])[:, v].sum() + (proj.depths * weights[2]).sum()
    )
    return proj, torch.autograd.grad(loss, params)


@pytest.mark.parametrize(("dtype", "rtol"), [(torch.float64, 1e-10), (torch.float32, 1e-3)])
def test_compiled_projection_matches_the_reference_with_gradients(dtype, rtol):
    ref, ref_grads = _project(project_gaussians, dtype)
    out, grads = _project(project_gaussians_numba, dtype)
    assert torch.equal(out.valid, ref.valid)
    assert 0 < int(ref.valid.sum()) < len(ref.valid)  # both culled and kept Gaussians
    v = ref.valid
    atol = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(out.means2d[v], ref.means2d[v], rtol=rtol, atol=atol)
    torch.testing.assert_close(out.depths, ref.depths, rtol=rtol, atol=atol)
    torch.testing.assert_close(out.conics[:, v], ref.conics[:, v], rtol=rtol, atol=atol)
    torch.testing.assert_close(out.half_extent[:, v], ref.half_extent[:, v], rtol=rtol, atol=atol)
    for got, want in zip(grads, ref_grads):
        scale = float(want.abs().max())
        torch.testing.assert_close(got, want, rtol=rtol, atol=rtol * scale)


def test_compiled_projection_gradcheck():
    means, quats, scales, opacities = _gaussians(12, torch.float64, seed=3)
    means, quats, scales = means[8:], quats[8:], scales[8:]  # in front, one with a clamped Jacobian
    K = CAMERA.to_torch(device="cpu", dtype=torch.float64)["K"]
    vm = _viewmat(torch.float64)

    def f(m, q, s):
        p = project_gaussians_numba(m, q, s, opacities[8:], vm, K, CAMERA.width, CAMERA.height)
        return p.means2d, p.conics, p.depths

    inputs = tuple(t.clone().requires_grad_(True) for t in (means, quats, scales))
    assert torch.autograd.gradcheck(f, inputs)


@pytest.mark.parametrize(("tile_size", "rows"), [(8, None), (16, None), (8, (48, 88))])
def test_compiled_binning_equals_the_reference(tile_size, rows):
    means, quats, scales, opacities = _gaussians(2000, torch.float32, seed=5)
    means[20:40] = means[40:60]  # equal depths: ties keep the index order
    quats[20:40], scales[20:40] = quats[40:60], scales[40:60]
    K = CAMERA.to_torch(device="cpu", dtype=torch.float32)["K"]
    with torch.no_grad():
        p = project_gaussians(means, quats, scales, opacities, _viewmat(torch.float32), K, CAMERA.width, CAMERA.height)
    y0, y1 = rows if rows is not None else (0, CAMERA.height)
    args = (p.means2d, p.half_extent, p.depths, p.valid, CAMERA.width, y1 - y0, tile_size)
    want = bin_gaussians(*args, row0=y0)
    got = bin_gaussians_numba(*args, row0=y0)
    assert want.pair_gid.numel() > 1000
    for name in ("pair_gid", "pair_tile", "tile_start", "tile_len", "radii"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype and torch.equal(a, b), name
    assert (got.tiles_x, got.tiles_y, got.tile_size, got.row0) == (want.tiles_x, want.tiles_y, want.tile_size, y0)


def _pairs(dtype: torch.dtype, rows=None):
    """Projected Gaussians (as leaves) and their bins; one opacity underflows the log's clamp."""
    means, quats, scales, opacities = _gaussians(400, dtype, seed=7)
    K = CAMERA.to_torch(device="cpu", dtype=dtype)["K"]
    with torch.no_grad():
        p = project_gaussians(means, quats, scales, opacities, _viewmat(dtype), K, CAMERA.width, CAMERA.height)
    y0, y1 = rows if rows is not None else (0, CAMERA.height)
    bins = bin_gaussians(p.means2d, p.half_extent, p.depths, p.valid, CAMERA.width, y1 - y0, 8, row0=y0)
    opacities = opacities.clone()
    opacities[int(bins.pair_gid[0])] = 1e-35  # below the clamp: no gradient, as the reference
    return p.means2d, p.conics, opacities, bins


@pytest.mark.parametrize(("dtype", "rtol"), [(torch.float64, 1e-10), (torch.float32, 1e-4)])
@pytest.mark.parametrize("rows", [None, (48, 88)])
def test_compiled_pair_coefficients_match_the_reference_with_gradients(dtype, rtol, rows):
    means2d, conics, opacities, bins = _pairs(dtype, rows)
    assert bins.pair_gid.numel() > 1000
    g = torch.Generator().manual_seed(2)
    upstream = torch.randn(6, bins.pair_gid.numel(), generator=g, dtype=dtype)
    results = []
    for fn in (pair_coefficients, pair_coefficients_numba):
        leaves = [t.clone().requires_grad_(True) for t in (means2d, conics, opacities)]
        kp = fn(*leaves, bins)
        results.append((kp.detach(), torch.autograd.grad((kp * upstream).sum(), leaves)))
    (want, want_grads), (got, got_grads) = results
    assert got.dtype == dtype and got.shape == want.shape
    torch.testing.assert_close(got, want, rtol=rtol, atol=rtol * float(want.abs().max()))
    for a, b in zip(got_grads, want_grads):
        torch.testing.assert_close(a, b, rtol=rtol, atol=rtol * float(b.abs().max()))
    assert float(got_grads[2][int(bins.pair_gid[0])]) == 0.0


def test_compiled_pair_coefficients_gradcheck():
    means2d, conics, opacities, bins = _pairs(torch.float64)
    keep = bins.pair_gid < 60  # a few Gaussians' pairs, each with several tiles
    small = type(bins)(**{**bins.__dict__, "pair_gid": bins.pair_gid[keep], "pair_tile": bins.pair_tile[keep]})
    n = 60
    inputs = tuple(t[..., :n].clone() if t is conics else t[:n].clone() for t in (means2d, conics, opacities))
    inputs = tuple(t.requires_grad_(True) for t in inputs)
    assert small.pair_gid.numel() > 20
    assert torch.autograd.gradcheck(lambda m, c, o: pair_coefficients_numba(m, c, o, small), inputs)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_compiled_sh_colours_match_the_reference_with_gradients(dtype, degree):
    g = torch.Generator().manual_seed(degree)
    n = 300
    sh = torch.randn(n, 16, 3, generator=g, dtype=dtype) * 0.5  # many colours clamped at 0
    dirs = torch.randn(n, 3, generator=g, dtype=dtype) * 3.0
    dirs[0] = 0.0  # no direction, and one below the length floor: the reference's 1e-12 rule
    dirs[1] = torch.tensor([1e-13, -2e-13, 0.0], dtype=dtype)
    weights = torch.randn(n, 3, generator=g, dtype=dtype)
    results = []
    for fn in (eval_sh, eval_sh_torch):
        s, d = sh.clone().requires_grad_(True), dirs.clone().requires_grad_(True)
        colours = fn(s, d, degree)
        g_sh, g_dirs = torch.autograd.grad((colours * weights).sum(), (s, d), allow_unused=True)
        results.append((colours, g_sh, torch.zeros_like(dirs) if g_dirs is None else g_dirs))
    (got, got_sh, got_dirs), (want, want_sh, want_dirs) = results
    assert 0 < int((want == 0).sum()) or degree == 0
    tol = dict(rtol=1e-12, atol=1e-12) if dtype == torch.float64 else dict(rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(got, want, **tol)
    torch.testing.assert_close(got_sh, want_sh, **tol)
    scale = float(want_dirs.abs().max()) or 1.0
    torch.testing.assert_close(got_dirs, want_dirs, rtol=tol["rtol"], atol=tol["atol"] * scale)


def test_eval_sh_takes_the_compiled_path_on_cpu():
    sh = torch.randn(4, 16, 3)
    dirs = torch.randn(4, 3)
    k = num_sh_bases(2)
    # The extra bands are dropped before the kernel: equal to the kernel on the first k.
    torch.testing.assert_close(eval_sh(sh, dirs, 2), sh_colors(sh[:, :k].contiguous(), dirs), rtol=0, atol=0)
