"""Rasterizer tests: float64 gradcheck, agreement with the brute-force reference (values and
gradients), hand-computed compositing rules, camera convention, culling, SH."""

from __future__ import annotations

import math
import sys
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from n2f2.cameras import Camera, look_at
from n2f2.errors import N2F2Error
from n2f2.render import rasterize, rasterize_in_bands, render_rgb
from n2f2.render.reference import rasterize_reference
from n2f2.render.sh import SH_C0, eval_sh, sh_basis
from n2f2.render.torch_backend import rasterize_torch

# The CPU backends: both are judged against the brute-force reference and by hand-worked rules.
CPU_BACKENDS = ["torch", "numba"]


def _camera(width=32, height=24, focal=30.0) -> Camera:
    R, t = look_at(np.array([0.3, -3.0, 0.6]), np.zeros(3))
    return Camera(focal, focal * 1.1, width / 2 + 0.7, height / 2 - 0.4, width, height, R=R, t=t)


def _scene(n, channels=3, dtype=torch.float64, seed=0, opacity=(0.05, 0.95), scale=(0.02, 0.17)):
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * 1.6
    quats = torch.randn(n, 4, generator=g, dtype=dtype)
    scales = torch.rand(n, 3, generator=g, dtype=dtype) * (scale[1] - scale[0]) + scale[0]
    opac = torch.rand(n, generator=g, dtype=dtype) * (opacity[1] - opacity[0]) + opacity[0]
    feats = torch.rand(n, channels, generator=g, dtype=dtype)
    return [means, quats, scales, opac, feats]


def _outputs(out):
    return out.features, out.alpha, out.depth


def _compare(params, camera, rtol, atol, grad_rtol, grad_atol, backend="torch", **kw):
    params = [p.clone().requires_grad_() for p in params]
    if backend == "torch":
        out = rasterize_torch_out(params, camera, **kw)
    else:
        kw = {k: v for k, v in kw.items() if k not in ("chunk", "batch_elements")}
        out = rasterize(*params, camera, backend=backend, **kw)
    ref = rasterize_reference(*params, camera, **{k: v for k, v in kw.items() if k not in ("chunk", "batch_elements", "tile_size")})
    for a, b in zip(_outputs(out), _outputs(ref)):
        torch.testing.assert_close(a, b, rtol=rtol, atol=atol)
    out.means2d.retain_grad()
    ref.means2d.retain_grad()
    g = torch.Generator().manual_seed(1)
    weights = [torch.randn(x.shape, generator=g, dtype=x.dtype) for x in _outputs(ref)]
    loss_out = sum((x * w).sum() for x, w in zip(_outputs(out), weights))
    loss_ref = sum((x * w).sum() for x, w in zip(_outputs(ref), weights))
    grads_out = torch.autograd.grad(loss_out, params + [out.means2d])
    grads_ref = torch.autograd.grad(loss_ref, params + [ref.means2d])
    for name, a, b in zip(["means", "quats", "scales", "opacities", "features", "means2d"], grads_out, grads_ref):
        scale = b.abs().max().clamp_min(1e-12)
        torch.testing.assert_close(a / scale, b / scale, rtol=grad_rtol, atol=grad_atol, msg=lambda m: f"{name}: {m}")
    return out, ref


def rasterize_torch_out(params, camera, chunk=128, batch_elements=1 << 17, tile_size=8, **kw):
    """The torch backend with its internal chunking exposed, wrapped like rasterize()."""
    from n2f2.render import RenderOutput

    cam = camera.to_torch(dtype=params[0].dtype)
    raw = rasterize_torch(*params, cam["viewmat"], cam["K"], camera.width, camera.height,
                          chunk=chunk, batch_elements=batch_elements, tile_size=tile_size, **kw)
    alpha = raw["alpha"]
    depth = torch.where(alpha > 0, raw["depth_sum"] / alpha.clamp_min(1e-30), torch.zeros_like(alpha))
    return RenderOutput(raw["features"], alpha, depth, raw["means2d"], raw["radii"], raw["n_pairs"])


# ----------------------------------------------------------------------------------- gradcheck
@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_gradcheck_float64(backend):
    camera = _camera(16, 12, focal=14.0)
    params = _scene(5, channels=2, opacity=(0.2, 0.8), scale=(0.15, 0.4), seed=3)
    params = [p.requires_grad_() for p in params]

    def fn(means, quats, scales, opac, feats):
        out = rasterize(means, quats, scales, opac, feats, camera, backend=backend)
        return out.features, out.alpha, out.depth

    assert fn(*params)[1].max() > 0.3  # the scene is actually visible
    # fast_mode checks random projections of the Jacobian (one backward pass per check instead
    # of one per output pixel), which keeps this under a few seconds.
    assert torch.autograd.gradcheck(fn, params, eps=1e-6, atol=1e-5, rtol=1e-4, fast_mode=True)


# ------------------------------------------------------------------------- vs the reference
@pytest.mark.parametrize("backend", CPU_BACKENDS)
@pytest.mark.parametrize("channels", [1, 3, 64])
def test_matches_reference_float64(channels, backend):
    out, _ = _compare(_scene(50, channels), _camera(), rtol=1e-10, atol=1e-10, grad_rtol=1e-8, grad_atol=1e-9, backend=backend)
    assert out.alpha.max() > 0.9


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_matches_reference_float32(backend):
    params = [p.float() for p in _scene(50, 3)]
    _compare(params, _camera(), rtol=1e-4, atol=1e-4, grad_rtol=1e-3, grad_atol=1e-3, backend=backend)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_matches_reference_many_chunks_batches_and_termination(backend):
    # Chunks of 4 Gaussians and 1-tile batches exercise the carried transmittance, the early stop
    # and the dropping of finished tiles; opaque Gaussians (clamped at 0.99) make pixels stop.
    params = _scene(80, 3, opacity=(0.5, 0.999), scale=(0.1, 0.3), seed=5)
    out, _ = _compare(params, _camera(), rtol=1e-10, atol=1e-10, grad_rtol=1e-8, grad_atol=1e-9,
                      chunk=4, batch_elements=1, backend=backend)
    assert out.alpha.max() > 1 - 1e-3  # some pixels reached termination


@pytest.mark.parametrize("backend", CPU_BACKENDS)
@pytest.mark.parametrize("tile_size", [4, 16])
def test_tile_size_does_not_change_the_image(tile_size, backend):
    params = _scene(40, 3, seed=7)
    a = rasterize(*params, _camera(), backend=backend, tile_size=8)
    b = rasterize(*params, _camera(), backend=backend, tile_size=tile_size)
    for x, y in zip(_outputs(a), _outputs(b)):
        torch.testing.assert_close(x, y, rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------- rules checked by hand
def test_camera_rows_is_a_crop_of_the_image():
    cam = _camera(width=32, height=40)
    crop = cam.rows(16, 32)
    assert (crop.width, crop.height) == (32, 16)
    pts = np.array([[0.1, 0.2, 0.3], [-0.4, 0.0, 0.5]])
    (uv, z), (uv_c, z_c) = cam.project(pts), crop.project(pts)
    np.testing.assert_allclose(uv_c, uv - [0.0, 16.0], atol=1e-12)  # same column, 16 rows up
    np.testing.assert_allclose(z_c, z)
    with pytest.raises(ValueError):
        cam.rows(32, 48)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_rendering_in_bands_equals_one_pass(backend):
    # 70 rows in bands of 16 (the smallest band: a 1-byte budget), the last one 6 rows; large
    # Gaussians cross every band boundary. The reference is the brute-force renderer.
    cam = _camera(width=40, height=70, focal=45.0)
    params = _scene(60, channels=5, dtype=torch.float64, scale=(0.05, 0.3))
    ref = rasterize_reference(*params, cam)
    buf = torch.full((70, 40, 5), float("nan"), dtype=torch.float64)
    out = rasterize_in_bands(*params, cam, max_band_bytes=1, out=buf, backend=backend)
    assert out.features.data_ptr() == buf.data_ptr()
    for a, b in zip(_outputs(out), _outputs(ref)):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-10)
    one = rasterize(*params, cam, backend=backend)  # the same projection and tiles
    for a, b in zip(_outputs(out), _outputs(one)):
        if backend == "numba":  # per-pixel loops over the same lists: bit for bit
            assert torch.equal(a, b)
        else:  # the torch backend batches tiles differently: sums may round differently
            torch.testing.assert_close(a, b, rtol=0, atol=1e-13)
    assert torch.equal(out.means2d, one.means2d) and torch.equal(out.radii, one.radii)
    with pytest.raises(ValueError, match="shape"):
        rasterize_in_bands(*params, cam, out=torch.empty(70, 40, 4, dtype=torch.float64))


def _axis_camera(size=16):
    # Identity pose; principal point on the centre of pixel (8, 8).
    return Camera(20.0, 20.0, 8.5, 8.5, size, size)


def _stack_on_axis(opacities, scale=0.5):
    n = len(opacities)
    dt = torch.float64
    means = torch.tensor([[0.0, 0.0, 2.0 + i] for i in range(n)], dtype=dt)
    quats = torch.tensor([[1.0, 0, 0, 0]] * n, dtype=dt)
    scales = torch.full((n, 3), scale, dtype=dt)
    return means, quats, scales, torch.tensor(opacities, dtype=dt), torch.eye(n, dtype=dt)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_alpha_clamp(backend):
    params = _stack_on_axis([0.999])
    out = rasterize(*params, _axis_camera(), backend=backend)
    assert out.alpha[8, 8, 0].item() == pytest.approx(0.99, abs=1e-12)
    out = rasterize(*params, _axis_camera(), backend=backend, alpha_clamp=0.5)
    assert out.alpha.max().item() == pytest.approx(0.5, abs=1e-12)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_early_termination_weights(backend):
    # Alphas 0.95 at the centre pixel: T = 0.05, 0.0025, 1.25e-4, then 6.25e-6 < 1e-4, so the
    # 4th Gaussian is not blended and the pixel stops (the 5th is not blended either).
    params = _stack_on_axis([0.95] * 5)
    out = rasterize(*params, _axis_camera(), backend=backend)
    expected = torch.tensor([0.95, 0.05 * 0.95, 0.0025 * 0.95, 0.0, 0.0], dtype=torch.float64)
    torch.testing.assert_close(out.features[8, 8], expected, rtol=1e-12, atol=1e-15)
    assert out.alpha[8, 8, 0].item() == pytest.approx(1 - 1.25e-4, abs=1e-12)
    expected_depth = (expected[:3] * torch.tensor([2.0, 3.0, 4.0], dtype=torch.float64)).sum() / (1 - 1.25e-4)
    assert out.depth[8, 8, 0].item() == pytest.approx(expected_depth.item(), rel=1e-12)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_alpha_cut_at_1_over_255(backend):
    # One isotropic Gaussian facing the camera: 2D variance (f s / z)^2 + 0.3, peak at (8.5, 8.5).
    o, s, z, f = 0.8, 0.05, 2.0, 20.0
    params = _stack_on_axis([o], scale=s)
    out = rasterize(*params, _axis_camera(), backend=backend)
    var = (f * s / z) ** 2 + 0.3
    c = torch.arange(16, dtype=torch.float64) + 0.5
    r2 = (c[None, :] - 8.5) ** 2 + (c[:, None] - 8.5) ** 2
    alpha = o * torch.exp(-0.5 * r2 / var)
    expected = torch.where(alpha >= 1 / 255, alpha, torch.zeros_like(alpha))
    assert (alpha < 1 / 255).any() and (alpha > 0).all()  # the cut matters here
    torch.testing.assert_close(out.alpha[..., 0], expected, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_behind_camera_and_near_plane_are_culled(backend):
    dt = torch.float64
    means = torch.tensor([[0.0, 0.0, -2.0], [0.0, 0.0, 0.005], [0.0, 0.0, 3.0]], dtype=dt)
    quats = torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=dt)
    scales = torch.tensor([[1.0] * 3, [1.0] * 3, [0.2] * 3], dtype=dt)
    opac = torch.full((3,), 0.9, dtype=dt)
    feats = torch.eye(3, dtype=dt)
    out = rasterize(means, quats, scales, opac, feats, _axis_camera(), backend=backend)
    assert out.radii[0] == 0 and out.radii[1] == 0 and out.radii[2] > 0
    assert out.features[..., :2].abs().max() == 0
    assert out.features[..., 2].max() > 0.5
    # Only the visible Gaussian receives gradients.
    means.requires_grad_()
    rasterize(means, quats, scales, opac, feats, _axis_camera(), backend=backend).features.sum().backward()
    assert means.grad[:2].abs().max() == 0 and means.grad[2].abs().max() > 0


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_empty_and_degenerate_inputs_give_finite_gradients(backend):
    dt = torch.float32
    empty = [torch.zeros(0, 3, dtype=dt), torch.zeros(0, 4, dtype=dt), torch.zeros(0, 3, dtype=dt),
             torch.zeros(0, dtype=dt), torch.zeros(0, 5, dtype=dt)]
    out = rasterize(*empty, _axis_camera(), backend=backend)
    assert out.features.shape == (16, 16, 5) and out.alpha.abs().max() == 0 and out.depth.abs().max() == 0
    # Behind the camera, and an opacity that underflowed to exactly 0.
    params = [torch.tensor([[0.0, 0, -1], [0, 0, 2]]), torch.tensor([[1.0, 0, 0, 0]] * 2),
              torch.full((2, 3), 0.1), torch.tensor([0.5, 0.0]), torch.ones(2, 3)]
    params = [p.requires_grad_() for p in params]
    out = rasterize(*params, _axis_camera(), backend=backend)
    (out.features.sum() + out.alpha.sum() + out.depth.sum()).backward()
    assert out.alpha.max() == 0 and (out.radii == 0).all()
    assert all(torch.isfinite(p.grad).all() for p in params)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_tiny_gaussian_lands_on_projected_pixel(backend):
    camera = _camera(40, 30)
    rng = np.random.default_rng(0)
    for _ in range(5):
        uv_target = rng.uniform([2, 2], [38, 28])
        p = camera.unproject(uv_target, np.array(rng.uniform(2.0, 4.0)))
        dt = torch.float64
        out = rasterize(torch.tensor(p[None], dtype=dt), torch.tensor([[1.0, 0, 0, 0]], dtype=dt),
                        torch.full((1, 3), 1e-4, dtype=dt), torch.tensor([0.9], dtype=dt),
                        torch.ones(1, 1, dtype=dt), camera, backend=backend)
        uv, _ = camera.project(p)
        row, col = np.unravel_index(int(out.alpha[..., 0].argmax()), out.alpha.shape[:2])
        assert (row, col) == (int(uv[1]), int(uv[0]))
        np.testing.assert_allclose(out.means2d[0].numpy(), uv, atol=1e-9)


@pytest.mark.parametrize("backend", CPU_BACKENDS)
def test_background_and_camera_list(backend):
    params = _scene(20, 3, seed=2)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)
    outs = rasterize(*params, [_camera(), _camera(16, 16)], backend=backend, background=bg)
    plain = rasterize(*params, _camera(), backend=backend)
    assert isinstance(outs, list) and outs[1].features.shape == (16, 16, 3)
    torch.testing.assert_close(outs[0].features, plain.features + bg * (1 - plain.alpha))


def test_backends_on_cpu():
    params = _scene(10, 3)
    with pytest.raises(N2F2Error):
        rasterize(*params, _camera(), backend="gsplat")
    had_gsplat = "gsplat" in sys.modules
    out = rasterize(*params, _camera(), backend="auto")
    assert out.n_pairs is not None  # a CPU backend ran
    assert ("gsplat" in sys.modules) == had_gsplat  # auto never imports gsplat for CPU tensors


def _gsplat_on_cuda() -> bool:
    if not torch.cuda.is_available():
        return False
    from n2f2.render.gsplat_backend import gsplat_usable

    return gsplat_usable(torch.device("cuda"))


@pytest.mark.skipif(not _gsplat_on_cuda(), reason="needs CUDA and gsplat")
def test_gsplat_matches_torch_backend_on_cuda():
    """Both backends on the GPU with gsplat's fixed alpha clamp: same image, alpha, depth and
    gradients (benchmarks/compare_gsplat.py prints the full comparison)."""
    from n2f2.render.reference import random_scene

    params, cam = random_scene(3000, 64, 16, device="cuda")
    outs, grads = [], []
    for backend in ("torch", "gsplat"):
        ps = [p.clone().requires_grad_() for p in params]
        out = rasterize(*ps, cam, backend=backend, alpha_clamp=0.999)
        (out.features.sum() + out.alpha.sum() + (out.depth * out.alpha).sum()).backward()
        outs.append(out)
        grads.append([p.grad for p in ps])
    (a, b), both = outs, (outs[0].alpha > 0.5) & (outs[1].alpha > 0.5)
    assert outs[1].n_pairs is None and a.n_pairs is not None  # each backend really ran
    torch.testing.assert_close(a.features, b.features, atol=1e-3, rtol=0)
    torch.testing.assert_close(a.alpha, b.alpha, atol=1e-3, rtol=0)
    torch.testing.assert_close(a.depth * both, b.depth * both, atol=1e-3 * float(a.depth.detach().max()), rtol=0)
    for ga, gb in zip(*grads):
        assert float((ga - gb).abs().max()) <= 1e-2 * float(ga.abs().max())


# ------------------------------------------------------------------------------------- SH
def test_sh_basis_is_orthonormal():
    # Fibonacci sphere: the mean of Y_i Y_j over the sphere times 4 pi is the identity.
    n = 20000
    i = torch.arange(n, dtype=torch.float64) + 0.5
    zc = 1 - 2 * i / n
    phi = math.pi * (1 + 5**0.5) * i
    r = torch.sqrt(1 - zc * zc)
    dirs = torch.stack([r * torch.cos(phi), r * torch.sin(phi), zc], -1)
    Y = sh_basis(dirs, 3)
    gram = Y.T @ Y * (4 * math.pi / n)
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=2e-3, rtol=0)


def test_eval_sh_known_values():
    sh = torch.zeros(2, 4, 3, dtype=torch.float64)
    sh[:, 0] = torch.tensor([1.0, -3.0, 0.0])
    sh[:, 2] = torch.tensor([1.0, 1.0, 1.0])  # the z band: +C1 z
    dirs = torch.tensor([[0.0, 0.0, 5.0], [0.0, 0.0, -1.0]], dtype=torch.float64)
    c1 = 0.4886025119029199
    sign = torch.tensor([[1.0], [-1.0]], dtype=torch.float64)  # z of the unit directions
    expected = (SH_C0 * sh[:, 0] + sign * c1 + 0.5).clamp_min(0)  # [[.., 0.142.., ..], [.., 0, ..]]
    assert expected[0, 1] > 0 and expected[1, 1] == 0  # the clamp acts on one entry only
    torch.testing.assert_close(eval_sh(sh, dirs, 1), expected)
    torch.testing.assert_close(eval_sh(sh, dirs, 0), (SH_C0 * sh[:, 0] + 0.5).clamp_min(0))


def test_eval_sh_gradcheck():
    g = torch.Generator().manual_seed(0)
    sh = torch.randn(4, 16, 3, generator=g, dtype=torch.float64, requires_grad=True)
    dirs = torch.randn(4, 3, generator=g, dtype=torch.float64, requires_grad=True)
    # Keep away from the clamp at 0 (not differentiable there).
    with torch.no_grad():
        sh[:, 0] += 3.0
    assert torch.autograd.gradcheck(lambda s, d: eval_sh(s, d, 3), (sh, dirs))


def test_render_rgb_duck_typed():
    means, quats, scales, opac, _ = _scene(20, 3, seed=4)
    sh = torch.randn(20, 16, 3, dtype=torch.float64) * 0.3
    gs = SimpleNamespace(means=means, quats=quats, scales=scales, opacities=opac, sh=sh, sh_degree=3)
    camera = _camera()
    out = render_rgb(gs, camera, backend="torch")
    colors = eval_sh(sh, means - torch.as_tensor(camera.center), 3)
    plain = rasterize(means, quats, scales, opac, colors, camera, backend="torch", background=(0.0, 0.0, 0.0))
    torch.testing.assert_close(out.features, plain.features)
    out0 = render_rgb(gs, camera, backend="torch", sh_degree=0, background=(1.0, 1.0, 1.0))
    colors0 = (SH_C0 * sh[:, 0] + 0.5).clamp_min(0)
    plain0 = rasterize(means, quats, scales, opac, colors0, camera, backend="torch", background=(1.0, 1.0, 1.0))
    torch.testing.assert_close(out0.features, plain0.features)


def test_numba_many_channels_long_lists_and_termination():
    # C = 64 as the semantic features: the numba kernels' channel loops in groups of four
    # pixels, tile lists walked past one gathered step of Gaussians, clamped alphas (opacity
    # up to 0.999) and early termination, all against the brute-force reference in float64.
    from n2f2.render.numba_backend import _CHUNK

    camera = _camera()
    params = _scene(250, 64, opacity=(0.05, 0.999), scale=(0.1, 0.4), seed=11)
    out, _ = _compare(params, camera, rtol=1e-10, atol=1e-10, grad_rtol=1e-8, grad_atol=1e-9, backend="numba")
    assert out.n_pairs > _CHUNK * camera.width * camera.height  # some pixels walked more than one step
    # A limit no pixel reaches (0.01^100 > 1e-300): every pixel walks its whole list.
    endless, _ = _compare(params, camera, rtol=1e-10, atol=1e-10, grad_rtol=1e-8, grad_atol=1e-9, backend="numba",
                          transmittance_min=1e-300)
    assert out.n_pairs < endless.n_pairs  # with the default limit, pixels stopped early


def test_numba_kernels_compile_in_a_child_process_and_the_first_render_waits(monkeypatch):
    # The child compiles (or loads from the disk cache) every kernel a pipeline uses and exits 0;
    # a render started meanwhile waits for the rasterizer's (and the fit's) first, and a process
    # starts only one child.
    from n2f2.pipeline.run import BACKGROUND_KERNELS
    from n2f2.render import numba_runtime as nb

    monkeypatch.setattr(nb, "_BACKGROUND", None)
    monkeypatch.setattr(nb, "_STARTED", False)
    nb.compile_in_background(**BACKGROUND_KERNELS)
    child = nb._BACKGROUND
    assert child is not None
    nb.compile_in_background()
    assert nb._BACKGROUND is child
    camera = _camera()
    params = _scene(20, 3, seed=2)
    rasterize(*params, camera, backend="numba")
    assert nb._BACKGROUND is None
    assert child.wait(timeout=300) == 0  # the later stages' kernels compiled as well
    assert nb.wait_for_background_compile() is None
    nb.compile_in_background()  # the next pipeline in this process starts no second child
    assert nb._BACKGROUND is None


@pytest.mark.parametrize(
    ("first", "later", "expected"), [((), ("n2f2.no_such_module",), 0), (("n2f2.no_such_module",), (), 1)]
)
def test_the_first_render_waits_for_the_first_kernels_only(monkeypatch, first, later, expected):
    # A module that fails after the rasterizer and the first modules are compiled does not hold
    # up the first render (it waits for the "ready" line); one that fails before is the child's
    # exit code, and the render compiles what it needs itself.
    from n2f2.render import numba_runtime as nb

    monkeypatch.setattr(nb, "_BACKGROUND", None)
    monkeypatch.setattr(nb, "_STARTED", False)
    nb.compile_in_background(first=first, later=later)
    child = nb._BACKGROUND
    assert child is not None
    assert nb.wait_for_background_compile() == expected
    assert child.wait(timeout=300) == 1  # the missing module fails the child either way


def test_torch_on_one_thread_keeps_the_kernels_threads_and_restores_torch():
    # Inside: torch's operations on one thread, the compiled render on the threads torch had, and
    # a render equal to one outside; after (also after an error, and when nested) torch's count is back.
    from n2f2.render import numba_runtime as nb

    pytest.importorskip("numba")
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        camera = _camera()
        params = _scene(40, 3, seed=4)
        outside = rasterize(*params, camera, backend="numba").features
        with nb.torch_on_one_thread():
            assert torch.get_num_threads() == 1 and nb.kernel_threads() == 2
            with nb.torch_on_one_thread():
                assert torch.get_num_threads() == 1 and nb.kernel_threads() == 2
            assert torch.get_num_threads() == 1 and nb.kernel_threads() == 2
            inside = rasterize(*params, camera, backend="numba").features
        torch.testing.assert_close(inside, outside, rtol=0, atol=0)
        assert torch.get_num_threads() == 2 and nb.kernel_threads() == 2
        with pytest.raises(RuntimeError), nb.torch_on_one_thread():
            raise RuntimeError("stop")
        assert torch.get_num_threads() == 2 and nb._KERNEL_THREADS is None
        torch.set_num_threads(1)
        assert nb.kernel_threads() == 1  # outside the context the kernels follow torch again
    finally:
        torch.set_num_threads(before)
