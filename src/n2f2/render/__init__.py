"""Differentiable Gaussian splatting: features of any width, alpha and expected z-depth.

Backends:

* ``"torch"``: pure PyTorch, tiled, custom backward (:mod:`n2f2.render.torch_backend`); any device.
* ``"numba"``: the torch backend's projection and binning with compiled compositing
  (:mod:`n2f2.render.numba_backend`); CPU tensors only.
* ``"gsplat"``: CUDA kernels of gsplat (:mod:`n2f2.render.gsplat_backend`); CUDA tensors only.
* ``"auto"`` (default): gsplat for CUDA tensors when gsplat imports, numba for CPU tensors when
  numba imports, the torch backend otherwise (gsplat is never imported on CPU, so no JIT CUDA
  build is attempted).

Conventions are those of :mod:`n2f2.cameras` (OpenCV axes, pixel centres at +0.5, z-depth).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence, overload

import torch
from torch import Tensor

from n2f2.cameras import Camera
from n2f2.errors import N2F2Error
from n2f2.render.sh import eval_sh, num_sh_bases

__all__ = ["RenderOutput", "rasterize", "rasterize_in_bands", "render_rgb", "view_colors", "eval_sh", "num_sh_bases"]

BACKENDS = ("auto", "torch", "numba", "gsplat")


@dataclass
class RenderOutput:
    """One rendered view."""

    features: Tensor  # [H, W, C] composited features (+ background * (1 - alpha) if given)
    alpha: Tensor  # [H, W, 1] accumulated opacity 1 - T_final
    depth: Tensor  # [H, W, 1] expected z-depth sum(w z) / sum(w); 0 where alpha == 0
    means2d: Tensor  # [N, 2] projected centres (u, v); non-leaf, on the autograd path
    radii: Tensor  # [N] int32 screen radius in pixels, 0 = culled / touches no pixel
    n_pairs: int | None = None  # pixel-Gaussian pairs evaluated (CPU backends; benchmarks)


def _check_inputs(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, features: Tensor) -> None:
    n = means.shape[0] if means.dim() == 2 else -1
    expected = {
        "means": (means, (n, 3)),
        "quats": (quats, (n, 4)),
        "scales": (scales, (n, 3)),
        "opacities": (opacities, (n,)),
    }
    for name, (x, shape) in expected.items():
        if tuple(x.shape) != shape:
            raise ValueError(f"rasterize: {name} must have shape {shape} with N = len(means), got {tuple(x.shape)}")
    if features.dim() != 2 or features.shape[0] != n:
        raise ValueError(f"rasterize: features must have shape [N, C] with N = {n}, got {tuple(features.shape)}")
    for name, x in (("quats", quats), ("scales", scales), ("opacities", opacities), ("features", features)):
        if x.device != means.device or x.dtype != means.dtype:
            raise ValueError(f"rasterize: {name} is {x.dtype} on {x.device}, means is {means.dtype} on {means.device}")


@overload
def rasterize(
    means: Tensor,  # [N, 3] world-space centres
    quats: Tensor,  # [N, 4] wxyz rotations (normalised inside)
    scales: Tensor,  # [N, 3] standard deviations (actual scales, not log)
    opacities: Tensor,  # [N] in (0, 1)
    features: Tensor,  # [N, C] any C
    camera: Camera,
    *,
    backend: str = "auto",
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,  # low-pass dilation added to the 2D covariance (pixels^2)
    alpha_clamp: float = 0.99,  # per-Gaussian alpha cap (3DGS; gsplat has 0.999 built in)
    alpha_min: float = 1.0 / 255.0,  # alphas below are skipped
    transmittance_min: float = 1e-4,  # early termination threshold
    tile_size: int = 8,  # torch backend only
    background: Tensor | Sequence[float] | None = None,  # [C]
    rows: tuple[int, int] | None = None,  # only image rows [y0, y1), y0 a multiple of tile_size (CPU backends)
) -> RenderOutput: ...


@overload
def rasterize(
    means: Tensor,  # [N, 3] world-space centres
    quats: Tensor,  # [N, 4] wxyz rotations (normalised inside)
    scales: Tensor,  # [N, 3] standard deviations (actual scales, not log)
    opacities: Tensor,  # [N] in (0, 1)
    features: Tensor,  # [N, C] any C
    camera: Sequence[Camera],
    *,
    backend: str = "auto",
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,  # low-pass dilation added to the 2D covariance (pixels^2)
    alpha_clamp: float = 0.99,  # per-Gaussian alpha cap (3DGS; gsplat has 0.999 built in)
    alpha_min: float = 1.0 / 255.0,  # alphas below are skipped
    transmittance_min: float = 1e-4,  # early termination threshold
    tile_size: int = 8,  # torch backend only
    background: Tensor | Sequence[float] | None = None,  # [C]
    rows: tuple[int, int] | None = None,  # only image rows [y0, y1), y0 a multiple of tile_size (CPU backends)
) -> list[RenderOutput]: ...


def rasterize(
    means: Tensor,  # [N, 3] world-space centres
    quats: Tensor,  # [N, 4] wxyz rotations (normalised inside)
    scales: Tensor,  # [N, 3] standard deviations (actual scales, not log)
    opacities: Tensor,  # [N] in (0, 1)
    features: Tensor,  # [N, C] any C
    camera: Camera | Sequence[Camera],
    *,
    backend: str = "auto",
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,  # low-pass dilation added to the 2D covariance (pixels^2)
    alpha_clamp: float = 0.99,  # per-Gaussian alpha cap (3DGS; gsplat has 0.999 built in)
    alpha_min: float = 1.0 / 255.0,  # alphas below are skipped
    transmittance_min: float = 1e-4,  # early termination threshold
    tile_size: int = 8,  # torch backend only
    background: Tensor | Sequence[float] | None = None,  # [C]
    rows: tuple[int, int] | None = None,  # only image rows [y0, y1), y0 a multiple of tile_size (CPU backends)
) -> RenderOutput | list[RenderOutput]:
    """Render Gaussians carrying ``features`` from ``camera`` (a list of cameras -> a list).

    Works in float32 and float64 on the inputs' device; gradients reach means, quats, scales,
    opacities and features. ``out.means2d.retain_grad()`` before ``backward`` gives the
    screen-space positional gradient used for densification."""
    if not isinstance(camera, Camera):
        return [
            rasterize(
                means,
                quats,
                scales,
                opacities,
                features,
                cam,
                backend=backend,
                near=near,
                far=far,
                eps2d=eps2d,
                alpha_clamp=alpha_clamp,
                alpha_min=alpha_min,
                transmittance_min=transmittance_min,
                tile_size=tile_size,
                background=background,
                rows=rows,
            )
            for cam in camera
        ]
    if backend not in BACKENDS:
        raise N2F2Error(f"unknown render backend {backend!r}; choose one of {', '.join(BACKENDS)}")
    if not 0.0 < alpha_min <= alpha_clamp < 1.0:
        raise ValueError(f"need 0 < alpha_min <= alpha_clamp < 1, got {alpha_min}, {alpha_clamp}")
    if not 0.0 < near < far:
        raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
    if not 0.0 < transmittance_min < 1.0 or tile_size < 1:
        raise ValueError(f"need 0 < transmittance_min < 1 and tile_size >= 1, got {transmittance_min}, {tile_size}")
    _check_inputs(means, quats, scales, opacities, features)
    cam = camera.to_torch(device=means.device, dtype=means.dtype)
    if backend == "auto":
        from n2f2.render.gsplat_backend import gsplat_usable

        if gsplat_usable(means.device):
            backend = "gsplat"
        else:
            from n2f2.render.numba_runtime import numba_usable

            backend = "numba" if means.device.type == "cpu" and numba_usable() else "torch"
    if backend == "gsplat":
        from n2f2.render.gsplat_backend import rasterize_gsplat

        if rows is not None:
            raise ValueError("rasterize: rows (a band of the image) needs a CPU backend")

        raw = rasterize_gsplat(
            means,
            quats,
            scales,
            opacities,
            features,
            cam["viewmat"],
            cam["K"],
            camera.width,
            camera.height,
            near=near,
            far=far,
            eps2d=eps2d,
        )
    else:
        if backend == "numba":
            from n2f2.render.numba_backend import rasterize_numba as rasterize_cpu
        else:
            from n2f2.render.torch_backend import rasterize_torch as rasterize_cpu

        raw = rasterize_cpu(
            means,
            quats,
            scales,
            opacities,
            features,
            cam["viewmat"],
            cam["K"],
            camera.width,
            camera.height,
            near=near,
            far=far,
            eps2d=eps2d,
            alpha_clamp=alpha_clamp,
            alpha_min=alpha_min,
            transmittance_min=transmittance_min,
            tile_size=tile_size,
            rows=rows,
        )
    alpha = raw["alpha"]
    dsum = raw["depth_sum"]
    # Expected depth; where nothing was blended alpha is exactly 0 and so is the depth sum.
    depth = torch.where(alpha > 0, dsum / alpha.clamp_min(1e-30), torch.zeros_like(dsum))
    feats = raw["features"]
    if background is not None:
        bg = torch.as_tensor(background, dtype=feats.dtype, device=feats.device)
        feats = feats + bg * (1.0 - alpha)
    return RenderOutput(
        features=feats, alpha=alpha, depth=depth, means2d=raw["means2d"], radii=raw["radii"], n_pairs=raw.get("n_pairs")
    )


@torch.no_grad()
def rasterize_in_bands(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] wxyz
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    features: Tensor,  # [N, C]
    camera: Camera,
    *,
    max_band_bytes: int = 16 * 2**20,
    out: Tensor | None = None,  # [H, W, C], written in place; allocated when None
    **kw: Any,  # rasterize()'s options
) -> RenderOutput:
    """:func:`rasterize` for inference, with working memory bounded by a band, not the image.

    On CPU the image is rendered in bands of whole tile rows (``rasterize(rows=...)``), each
    band's features written into ``out``: a render's transient memory (the compositing's tiled
    output and its untiled copy, about three ``[h, W, C + 2]`` arrays) then stays near
    ``max_band_bytes`` whatever the image size, and the result is the one-pass image (same
    projection, same tiles; the torch backend's batches of tiles may round sums differently).
    ``radii`` are the largest over the bands (0: touches no pixel). On CUDA (gsplat) it renders
    in one pass into ``out``. No gradients."""
    H, W, C = camera.height, camera.width, features.shape[1]
    if out is None:
        out = features.new_empty(H, W, C)
    elif tuple(out.shape) != (H, W, C) or out.dtype != features.dtype or out.device != features.device:
        raise ValueError(
            f"out must be a {features.dtype} tensor of shape {(H, W, C)} on {features.device}, "
            f"got {out.dtype} {tuple(out.shape)} on {out.device}"
        )
    if means.device.type != "cpu":
        one = rasterize(means, quats, scales, opacities, features, camera, **kw)
        out.copy_(one.features)
        return RenderOutput(out, one.alpha, one.depth, one.means2d, one.radii, one.n_pairs)
    tile = int(kw.get("tile_size", 8))
    per_row = 3 * W * (C + 2) * features.element_size()
    rows = max(tile, (max_band_bytes // max(per_row, 1)) // tile * tile)
    alpha = features.new_empty(H, W, 1)
    depth = features.new_empty(H, W, 1)
    means2d, radii, pairs = None, None, 0
    for y0 in range(0, H, rows):
        y1 = min(H, y0 + rows)
        band = rasterize(means, quats, scales, opacities, features, camera, rows=(y0, y1), **kw)
        out[y0:y1] = band.features
        alpha[y0:y1] = band.alpha
        depth[y0:y1] = band.depth
        radii = band.radii if radii is None else torch.maximum(radii, band.radii)
        means2d = band.means2d
        pairs += band.n_pairs or 0
        del band
    # Camera heights are positive, so the loop ran at least once and set both.
    assert means2d is not None and radii is not None
    return RenderOutput(features=out, alpha=alpha, depth=depth, means2d=means2d, radii=radii, n_pairs=pairs)


def view_colors(
    gaussians: Any,  # has means [N, 3], sh [N, K, 3] and optionally sh_degree
    camera: Camera,
    sh_degree: int | None = None,  # default: gaussians.sh_degree (or the largest K allows)
) -> Tensor:  # [N, 3] colours seen from ``camera`` (view direction = camera centre -> Gaussian)
    """Per-Gaussian colours from spherical harmonics for one camera."""
    sh = gaussians.sh
    if sh_degree is None:
        sh_degree = getattr(gaussians, "sh_degree", None)
    if sh_degree is None:
        sh_degree = int(round(sh.shape[1] ** 0.5)) - 1
    means = gaussians.means
    center = torch.as_tensor(camera.center, dtype=means.dtype, device=means.device)
    return eval_sh(sh, means - center, int(sh_degree))


def render_rgb(
    gaussians: Any,  # has means [N,3], quats [N,4], scales [N,3], opacities [N], sh [N,K,3], sh_degree
    camera: Camera,
    *,
    sh_degree: int | None = None,  # default: gaussians.sh_degree (or the largest K allows)
    background: Tensor | Sequence[float] | None = (0.0, 0.0, 0.0),
    **kw: Any,  # passed to rasterize (backend, eps2d, alpha_clamp, ...)
) -> RenderOutput:
    """Render colours from spherical harmonics (:func:`view_colors`)."""
    return rasterize(
        gaussians.means,
        gaussians.quats,
        gaussians.scales,
        gaussians.opacities,
        view_colors(gaussians, camera, sh_degree),
        camera,
        background=background,
        **kw,
    )
