"""The per-pair ``log2 alpha`` coefficients compiled with numba:
:func:`n2f2.render.torch_backend.pair_coefficients`, one loop over the pairs forward and one
backward.

The torch function gathers six per-Gaussian rows for every (tile, Gaussian) pair and combines
them in some fifteen elementwise operations, and autograd walks twice as many backward, each a
pass over ``[M]`` tensors; at the demo fit's 40k pairs their fixed cost is the time. Here each
pair's six coefficients are computed in registers (float64 inside), and the backward sums each
pair's gradient into its Gaussian's centre, conic and opacity in one serial pass (pairs are
sorted by tile, so a Gaussian's pairs are spread out). The torch function stays the reference:
same values and gradients up to float rounding (tests compare both).
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from n2f2.render.numba_runtime import KERNEL_LOCK, numba_threads
from n2f2.render.torch_backend import Bins, pair_coefficients

try:  # optional at import time, as in the compositing kernels
    import numba
    from numba import njit, prange
except ImportError:  # pragma: no cover - numba is a declared dependency
    numba = None

_LOG2E = 1.0 / math.log(2.0)
_MIN_OPACITY = 1e-30  # the reference's clamp before the log

if numba is not None:

    @njit(cache=True, nogil=True, inline="always")
    def _centre(t, tiles_x, tile_size, row0):  # pixel coordinates of tile t's centre
        ty = t // tiles_x
        half = 0.5 * tile_size
        return np.float64((t - ty * tiles_x) * tile_size) + half, np.float64(ty * tile_size) + half + row0

    @njit(cache=True, nogil=True, inline="always")
    def _terms(means2d, conics, g, cx, cy):  # offset of the tile centre from Gaussian g, its conic
        dx = cx - np.float64(means2d[g, 0])
        dy = cy - np.float64(means2d[g, 1])
        return dx, dy, np.float64(conics[0, g]), np.float64(conics[1, g]), np.float64(conics[2, g])

    @njit(cache=True, nogil=True, parallel=True)
    def _forward_kernel(means2d, conics, opacities, gid, tile, tiles_x, tile_size, row0, out, nthreads):
        """out [6, M]: each pair's coefficients. Pairs come sorted by tile, so a thread's range
        finds its tile centre again only when the tile changes (an integer division per tile,
        not per pair)."""
        N, M = opacities.shape[0], gid.shape[0]
        logo = np.empty(N)
        for thread in prange(nthreads):
            for n in range(thread * N // nthreads, (thread + 1) * N // nthreads):
                logo[n] = math.log(max(np.float64(opacities[n]), _MIN_OPACITY))
        for thread in prange(nthreads):
            last, cx, cy = -1, 0.0, 0.0
            for m in range(thread * M // nthreads, (thread + 1) * M // nthreads):
                if tile[m] != last:
                    last = tile[m]
                    cx, cy = _centre(last, tiles_x, tile_size, row0)
                g = gid[m]
                dx, dy, a, b, c = _terms(means2d, conics, g, cx, cy)
                out[0, m] = _LOG2E * (logo[g] - 0.5 * a * dx * dx - b * dy * dx - 0.5 * c * dy * dy)
                out[1, m] = _LOG2E * (-a * dx - b * dy)
                out[2, m] = _LOG2E * (-b * dx - c * dy)
                out[3, m] = _LOG2E * (-0.5 * a)
                out[4, m] = _LOG2E * (-b)
                out[5, m] = _LOG2E * (-0.5 * c)

    @njit(cache=True, nogil=True)
    def _backward_kernel(means2d, conics, opacities, gid, tile, tiles_x, tile_size, row0, grad, g_m2d, g_con, g_op):
        """Sums over the pairs into g_m2d [N, 2], g_con [3, N], g_op [N] (float64, zeroed)."""
        last, cx, cy = -1, 0.0, 0.0
        for m in range(gid.shape[0]):
            if tile[m] != last:
                last = tile[m]
                cx, cy = _centre(last, tiles_x, tile_size, row0)
            g = gid[m]
            dx, dy, a, b, c = _terms(means2d, conics, g, cx, cy)
            k0 = _LOG2E * np.float64(grad[0, m])
            k1 = _LOG2E * np.float64(grad[1, m])
            k2 = _LOG2E * np.float64(grad[2, m])
            # d/d dx and d/d dy of the six coefficients; dx = centre - mean: d mean = -d dx.
            g_m2d[g, 0] -= k0 * (-a * dx - b * dy) - k1 * a - k2 * b
            g_m2d[g, 1] -= k0 * (-b * dx - c * dy) - k1 * b - k2 * c
            g_con[0, g] += -0.5 * k0 * dx * dx - k1 * dx - 0.5 * _LOG2E * np.float64(grad[3, m])
            g_con[1, g] += -k0 * dx * dy - k1 * dy - k2 * dx - _LOG2E * np.float64(grad[4, m])
            g_con[2, g] += -0.5 * k0 * dy * dy - k2 * dy - 0.5 * _LOG2E * np.float64(grad[5, m])
            g_op[g] += k0  # d coefficient 0 / d log(opacity), divided by the opacity below
        for n in range(g_op.shape[0]):
            o = np.float64(opacities[n])
            g_op[n] = g_op[n] / o if o >= _MIN_OPACITY else 0.0  # the clamp passes no gradient below


class _NumbaPairCoefficients(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, gid, tile, tiles_x, tile_size, row0):
        m2d, con, op = (t.detach().contiguous().numpy() for t in (means2d, conics, opacities))
        gid_np, tile_np = gid.contiguous().numpy(), tile.contiguous().numpy()
        out = np.empty((6, gid_np.shape[0]), m2d.dtype)
        with KERNEL_LOCK:
            _forward_kernel(m2d, con, op, gid_np, tile_np, tiles_x, tile_size, float(row0), out, numba_threads())
        ctx.saved = ((m2d, con, op), gid_np, tile_np, tiles_x, tile_size, float(row0))
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad):
        (m2d, con, op), gid, tile, tiles_x, tile_size, row0 = ctx.saved
        n = op.shape[0]
        g_m2d, g_con, g_op = np.zeros((n, 2)), np.zeros((3, n)), np.zeros(n)
        grad_np = grad.detach().to(torch.from_numpy(m2d).dtype).contiguous().numpy()
        with KERNEL_LOCK:
            _backward_kernel(m2d, con, op, gid, tile, tiles_x, tile_size, row0, grad_np, g_m2d, g_con, g_op)
        dtype = m2d.dtype
        out = (torch.from_numpy(g_m2d.astype(dtype)), torch.from_numpy(g_con.astype(dtype)))
        return (*out, torch.from_numpy(g_op.astype(dtype)), None, None, None, None, None)


def usable(means2d: Tensor) -> bool:
    """Whether the compiled coefficients take these inputs: CPU float tensors, numba present."""
    return numba is not None and means2d.device.type == "cpu" and means2d.dtype in (torch.float32, torch.float64)


def pair_coefficients_numba(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [3, N]
    opacities: Tensor,  # [N]
    bins: Bins,
) -> Tensor:  # [6, M]
    """:func:`~n2f2.render.torch_backend.pair_coefficients`, compiled (CPU; differentiable in
    the centres, conics and opacities, as the reference)."""
    if not usable(means2d):
        return pair_coefficients(means2d, conics, opacities, bins)
    dtype = means2d.dtype
    return _NumbaPairCoefficients.apply(
        means2d,
        conics.to(dtype),
        opacities.to(dtype),
        bins.pair_gid,
        bins.pair_tile,
        int(bins.tiles_x),
        int(bins.tile_size),
        bins.row0,
    )
