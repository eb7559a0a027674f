"""gsplat (CUDA) backend, imported lazily and only for CUDA tensors.

gsplat compiles its CUDA kernels at first use; on a machine without CUDA importing its
kernels triggers a JIT build attempt, so nothing here is imported unless
``torch.cuda.is_available()`` and the inputs live on a CUDA device.

Differences from the torch backend (compare accordingly):

* gsplat's alpha clamp is fixed at 0.999, alpha cut at 1/255 and the transmittance stop at 1e-4
  inside its kernels: ``alpha_clamp``, ``alpha_min`` and ``transmittance_min`` cannot be changed
  (run the torch backend with ``alpha_clamp=0.999`` to compare).
* gsplat's tile size is 16 (its only tested value); binning does not change the image.
* ``radii`` come from gsplat's own (opacity-aware) screen extent.

How far it differs from the torch backend on the same GPU: ``docs/measurements.md`` ("gsplat
against the torch backend").

The low-level gsplat functions are used rather than ``gsplat.rasterization`` so the ``[N, 2]``
``means2d`` we return is itself on the autograd path (``retain_grad()`` then works, as the
densification of 3DGS needs); ``render_mode`` is the equivalent of "RGB+ED" and
``rasterize_mode`` "classic" (no opacity compensation).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from n2f2.errors import N2F2Error

GSPLAT_TILE_SIZE = 16
GSPLAT_CHANNEL_CHUNK = 32  # gsplat's kernels are slow above 32 channels; render in chunks


def gsplat_usable(device: torch.device) -> bool:
    """True if gsplat can run for tensors on ``device`` (CUDA available and gsplat importable)."""
    if device.type != "cuda" or not torch.cuda.is_available():
        return False
    try:
        import gsplat  # noqa: F401  # pyright: ignore[reportMissingImports]  # optional, CUDA machines only
    except Exception:  # ImportError, or a missing transitive dependency such as `packaging`
        return False
    return True


def rasterize_gsplat(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] wxyz
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    features: Tensor,  # [N, C]
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    *,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
) -> dict:
    """Same dict as :func:`n2f2.render.torch_backend.rasterize_torch` (without n_pairs)."""
    if means.device.type != "cuda" or not torch.cuda.is_available():
        raise N2F2Error("the gsplat backend needs CUDA tensors and a CUDA device; use backend='torch'")
    try:
        from gsplat.cuda._wrapper import (  # pyright: ignore[reportMissingImports]  # optional, CUDA machines only
            fully_fused_projection,
            isect_offset_encode,
            isect_tiles,
            rasterize_to_pixels,
        )
    except ImportError as e:  # gsplat also needs `packaging`, which it does not declare
        raise N2F2Error(f"the gsplat backend needs `pip install gsplat packaging` ({e})") from e

    kw = dict(eps2d=eps2d, near_plane=near, far_plane=far, packed=False)
    try:  # gsplat >= 1.5 uses the opacities for a tighter screen extent
        proj = fully_fused_projection(
            means, None, quats, scales, viewmat[None], K[None], width, height, opacities=opacities, **kw
        )
    except TypeError:  # gsplat 1.4
        proj = fully_fused_projection(means, None, quats, scales, viewmat[None], K[None], width, height, **kw)
    radii, means2d, depths, conics, _ = (
        proj  # radii [1, N, 2] (gsplat < 1.5: [1, N]), means2d [1, N, 2], depths [1, N], conics [1, N, 3]
    )
    m2d = means2d[0]  # [N, 2]: the tensor we hand out; everything below reads it
    m2d_b = m2d[None]
    tiles_x = math.ceil(width / GSPLAT_TILE_SIZE)
    tiles_y = math.ceil(height / GSPLAT_TILE_SIZE)
    _, isect_ids, flatten_ids = isect_tiles(m2d_b, radii, depths, GSPLAT_TILE_SIZE, tiles_x, tiles_y)
    offsets = isect_offset_encode(isect_ids, 1, tiles_x, tiles_y)
    colors = torch.cat([features, depths[0][:, None]], dim=-1)[None]  # [1, N, C + 1], depth last
    opac = opacities[None]
    parts, alpha = [], None
    for c0 in range(0, colors.shape[-1], GSPLAT_CHANNEL_CHUNK):
        img, a = rasterize_to_pixels(
            m2d_b,
            conics,
            colors[..., c0 : c0 + GSPLAT_CHANNEL_CHUNK],
            opac,
            width,
            height,
            GSPLAT_TILE_SIZE,
            offsets,
            flatten_ids,
        )
        parts.append(img[0])
        alpha = a[0] if alpha is None else alpha
    img = torch.cat(parts, dim=-1)  # [H, W, C + 1]
    return {
        "features": img[..., :-1],
        "alpha": alpha,
        "depth_sum": img[..., -1:],
        "means2d": m2d,
        "radii": (radii[0].amax(-1) if radii.dim() == 3 else radii[0]).to(torch.int32),
        "n_pairs": None,
    }
