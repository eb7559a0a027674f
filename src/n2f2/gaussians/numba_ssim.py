"""The SSIM window's blur compiled with numba: :func:`n2f2.gaussians.optim.blur_reference`'s two
grouped ``conv2d`` passes (the reference) as one separable loop per map.

SSIM blurs five maps per colour channel (both images, their squares and their product) with an
11-tap Gaussian along each axis, zero padded. A grouped convolution of 15 thin maps is mostly
call overhead on a CPU (timings: ``docs/measurements.md``, "The SSIM window's blur compiled").
Here each map is one thread's: a source row is blurred along x into a buffer, and the buffer is
added into the (up to 11) output rows it reaches, so the map stays in cache. The blur is linear;
its backward is the same loop with the window reversed (a correlation's adjoint), so for the
symmetric Gaussian it is the same blur.
Sums follow another order than ``conv2d``'s: equal up to float rounding (tests compare both).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from n2f2.render.numba_runtime import KERNEL_LOCK, numba_threads

try:  # optional at import time, as in the rasterizer's kernels
    import numba
    from numba import njit, prange
except ImportError:  # pragma: no cover - numba is a declared dependency
    numba = None

if numba is not None:

    @njit(cache=True, nogil=True, parallel=True, fastmath={"contract"})
    def _blur(x, g, out, nthreads):
        """``out[k, i, j] = sum_{s, t} g[s] g[t] x[k, i + s - r, j + t - r]``, zero outside the
        map (r = len(g) // 2): x and out [K, H, W], g [S]."""
        K, H, W = x.shape
        S = g.shape[0]
        r = S // 2
        for thread in prange(nthreads):
            row = np.empty(W, dtype=x.dtype)  # one source row blurred along x
            for k in range(thread * K // nthreads, (thread + 1) * K // nthreads):
                o = out[k]
                o[:, :] = 0.0
                for i in range(H):
                    src = x[k, i]
                    row[:] = 0.0
                    for t in range(S):  # loops over slices from 0: no negative index to check
                        s = t - r
                        j0, j1 = max(0, -s), min(W, W - s)
                        acc, add, gt = row[j0:j1], src[j0 + s : j1 + s], g[t]
                        for j in range(j1 - j0):
                            acc[j] += gt * add[j]
                    # Source row i reaches output row i - (t - r) with weight g[t].
                    for t in range(max(0, i + r - H + 1), min(S, i + r + 1)):
                        dst, gt = o[i - t + r], g[t]
                        for j in range(W):
                            dst[j] += gt * row[j]


def usable(maps: Tensor) -> bool:
    """Whether the compiled blur takes ``maps``: a CPU float32 or float64 tensor, numba present."""
    return numba is not None and maps.device.type == "cpu" and maps.dtype in (torch.float32, torch.float64)


def _run(x: Tensor, g: Tensor) -> Tensor:  # [K, H, W], [S] -> [K, H, W]
    x = x.detach().contiguous()
    out = torch.empty_like(x)
    kernel = g.detach().to(x.dtype).contiguous().numpy()
    with KERNEL_LOCK:
        _blur(x.numpy(), kernel, out.numpy(), numba_threads())
    return out


class _Blur(torch.autograd.Function):
    @staticmethod
    def forward(ctx, maps: Tensor, g: Tensor) -> Tensor:
        ctx.save_for_backward(g)
        return _run(maps, g)

    @staticmethod
    def backward(ctx, grad: Tensor):  # pyright: ignore[reportIncompatibleMethodOverride]
        (g,) = ctx.saved_tensors
        return (_run(grad, g.flip(0)) if ctx.needs_input_grad[0] else None), None


def blur_numba(
    maps: Tensor,  # [K, H, W] CPU float32 or float64
    g: Tensor,  # [S] the window along each axis (S odd); no gradient flows to it
) -> Tensor:  # [K, H, W]
    """Each map correlated with ``g`` along x, then along y, zero padded: the compiled form of
    :func:`n2f2.gaussians.optim.blur_reference` (gradients flow to ``maps``)."""
    if maps.dim() != 3 or g.dim() != 1 or g.shape[0] % 2 != 1:
        raise ValueError(f"maps must be [K, H, W] and the window odd, got {tuple(maps.shape)} and {tuple(g.shape)}")
    return _Blur.apply(maps, g)


def warm_up() -> None:
    """Compile (or load from the cache) the blur with the argument types a fit step passes
    (:func:`n2f2.render.numba_runtime.compile_in_background` runs this)."""
    if numba is not None:
        maps = torch.rand(2, 5, 6, requires_grad=True)
        blur_numba(maps, torch.ones(3) / 3).sum().backward()
