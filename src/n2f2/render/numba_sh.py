"""Spherical-harmonics colours compiled with numba: the CPU fast path of :func:`n2f2.render.sh.eval_sh`.

The PyTorch form (:func:`n2f2.render.sh.eval_sh_torch`, the reference) builds the basis from
some forty elementwise operations on ``[N]`` tensors, and autograd runs as many again backward:
for the ten to twenty thousand Gaussians of a CPU fit, that costs more than the arithmetic. Here
one loop over the Gaussians does the forward, and one the backward, with the basis's derivatives
written out (3DGS's ``computeColorFromSH`` and its backward follow the same formulas).

Same contract and gradients as the reference (``sh`` and the directions, through their
normalisation and the clamp at 0), up to float rounding: the tests compare both paths.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from n2f2.render.numba_runtime import FASTMATH, numba_usable
from n2f2.render.sh_constants import SH_C0, SH_C1, SH_C2, SH_C3

try:  # optional at import time, as in the compositing kernels
    import numba
    from numba import njit
except ImportError:  # pragma: no cover - numba is a declared dependency
    numba = None

NORM_MIN = 1e-12  # the reference's floor on a direction's length

if numba is not None:
    A0 = SH_C0
    A1 = SH_C1
    B0, B1, B2, B3, B4 = SH_C2
    D0, D1, D2, D3, D4, D5, D6 = SH_C3

    @njit(fastmath=FASTMATH, cache=True, nogil=True)
    def _basis(x, y, z, K, out):  # out [K]: the 3DGS basis at the unit direction (x, y, z)
        out[0] = A0
        if K > 1:
            out[1] = -A1 * y
            out[2] = A1 * z
            out[3] = -A1 * x
        if K > 4:
            xx, yy, zz = x * x, y * y, z * z
            out[4] = B0 * x * y
            out[5] = B1 * y * z
            out[6] = B2 * (2 * zz - xx - yy)
            out[7] = B3 * x * z
            out[8] = B4 * (xx - yy)
            if K > 9:
                out[9] = D0 * y * (3 * xx - yy)
                out[10] = D1 * x * y * z
                out[11] = D2 * y * (4 * zz - xx - yy)
                out[12] = D3 * z * (2 * zz - 3 * xx - 3 * yy)
                out[13] = D4 * x * (4 * zz - xx - yy)
                out[14] = D5 * z * (xx - yy)
                out[15] = D6 * x * (xx - 3 * yy)

    @njit(fastmath=FASTMATH, cache=True, nogil=True)
    def _basis_grad(x, y, z, K, gb):  # gb [K] dL/dB_k -> dL/d(x, y, z) of the unit direction
        gx = -A1 * gb[3] if K > 1 else 0.0
        gy = -A1 * gb[1] if K > 1 else 0.0
        gz = A1 * gb[2] if K > 1 else 0.0
        if K > 4:
            gx += B0 * y * gb[4] - 2 * B2 * x * gb[6] + B3 * z * gb[7] + 2 * B4 * x * gb[8]
            gy += B0 * x * gb[4] + B1 * z * gb[5] - 2 * B2 * y * gb[6] - 2 * B4 * y * gb[8]
            gz += B1 * y * gb[5] + 4 * B2 * z * gb[6] + B3 * x * gb[7]
            if K > 9:
                xx, yy, zz = x * x, y * y, z * z
                gx += (
                    6 * D0 * x * y * gb[9]
                    + D1 * y * z * gb[10]
                    - 2 * D2 * x * y * gb[11]
                    - 6 * D3 * x * z * gb[12]
                    + D4 * (4 * zz - 3 * xx - yy) * gb[13]
                    + 2 * D5 * x * z * gb[14]
                    + 3 * D6 * (xx - yy) * gb[15]
                )
                gy += (
                    3 * D0 * (xx - yy) * gb[9]
                    + D1 * x * z * gb[10]
                    + D2 * (4 * zz - xx - 3 * yy) * gb[11]
                    - 6 * D3 * y * z * gb[12]
                    - 2 * D4 * x * y * gb[13]
                    - 2 * D5 * y * z * gb[14]
                    - 6 * D6 * x * y * gb[15]
                )
                gz += (
                    D1 * x * y * gb[10]
                    + 8 * D2 * y * z * gb[11]
                    + 3 * D3 * (2 * zz - xx - yy) * gb[12]
                    + 8 * D4 * x * z * gb[13]
                    + D5 * (xx - yy) * gb[14]
                )
        return gx, gy, gz

    # One thread: a kernel takes a few hundred microseconds for a fit's Gaussians, and handing it
    # to the thread pool between torch's operations cost more than it saved (a fit step measured).
    @njit(fastmath=FASTMATH, cache=True, nogil=True)
    def _forward_kernel(sh, dirs, out):  # sh [N, K, 3], dirs [N, 3] -> out [N, 3]
        K = sh.shape[1]
        b = np.empty(K, dtype=np.float64)
        for n in range(sh.shape[0]):
            vx, vy, vz = dirs[n, 0], dirs[n, 1], dirs[n, 2]
            r = max(np.sqrt(vx * vx + vy * vy + vz * vz), NORM_MIN)
            _basis(vx / r, vy / r, vz / r, K, b)
            s0 = s1 = s2 = 0.5
            for k in range(K):  # the row's coefficients in memory order
                s0 += b[k] * sh[n, k, 0]
                s1 += b[k] * sh[n, k, 1]
                s2 += b[k] * sh[n, k, 2]
            out[n, 0] = max(s0, 0.0)
            out[n, 1] = max(s1, 0.0)
            out[n, 2] = max(s2, 0.0)

    @njit(fastmath=FASTMATH, cache=True, nogil=True)
    def _backward_kernel(sh, dirs, g_out, g_sh, g_dirs):  # g_out [N, 3] -> g_sh [N, K, 3], g_dirs [N, 3]
        K = sh.shape[1]
        b = np.empty(K, dtype=np.float64)
        gb = np.empty(K, dtype=np.float64)
        for n in range(sh.shape[0]):
            vx, vy, vz = dirs[n, 0], dirs[n, 1], dirs[n, 2]
            norm = np.sqrt(vx * vx + vy * vy + vz * vz)
            r = max(norm, NORM_MIN)
            x, y, z = vx / r, vy / r, vz / r
            _basis(x, y, z, K, b)
            s0 = s1 = s2 = 0.5
            for k in range(K):
                s0 += b[k] * sh[n, k, 0]
                s1 += b[k] * sh[n, k, 1]
                s2 += b[k] * sh[n, k, 2]
            # The clamp at 0 passes the gradient where its input is >= 0 (as torch.clamp_min).
            g0 = g_out[n, 0] if s0 >= 0.0 else 0.0
            g1 = g_out[n, 1] if s1 >= 0.0 else 0.0
            g2 = g_out[n, 2] if s2 >= 0.0 else 0.0
            for k in range(K):
                gb[k] = sh[n, k, 0] * g0 + sh[n, k, 1] * g1 + sh[n, k, 2] * g2
                g_sh[n, k, 0] = b[k] * g0
                g_sh[n, k, 1] = b[k] * g1
                g_sh[n, k, 2] = b[k] * g2
            gx, gy, gz = _basis_grad(x, y, z, K, gb)
            if norm >= NORM_MIN:  # d = v / |v|: dL/dv = (g - d (d . g)) / |v|
                dot = x * gx + y * gy + z * gz
                g_dirs[n, 0] = (gx - x * dot) / r
                g_dirs[n, 1] = (gy - y * dot) / r
                g_dirs[n, 2] = (gz - z * dot) / r
            else:  # d = v / NORM_MIN: the length's floor has no gradient
                g_dirs[n, 0] = gx / r
                g_dirs[n, 1] = gy / r
                g_dirs[n, 2] = gz / r


class _ShColors(torch.autograd.Function):
    @staticmethod
    def forward(ctx, sh: Tensor, dirs: Tensor) -> Tensor:
        sh_np = sh.detach().contiguous().numpy()
        dirs_np = dirs.detach().contiguous().numpy()
        out = np.empty((sh_np.shape[0], 3), dtype=sh_np.dtype)
        _forward_kernel(sh_np, dirs_np, out)
        ctx.np, ctx.dtype = (sh_np, dirs_np), sh.dtype
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, g_out: Tensor):
        sh_np, dirs_np = ctx.np
        g_np = g_out.detach().to(ctx.dtype).contiguous().numpy()
        g_sh = np.empty_like(sh_np)
        g_dirs = np.empty_like(dirs_np)
        _backward_kernel(sh_np, dirs_np, g_np, g_sh, g_dirs)
        return torch.from_numpy(g_sh), torch.from_numpy(g_dirs)


def usable(sh: Tensor, dirs: Tensor) -> bool:
    """Whether the compiled path takes these inputs: CPU tensors of one float type, numba present."""
    return (
        numba_usable()
        and sh.device.type == "cpu"
        and dirs.device.type == "cpu"
        and sh.dtype in (torch.float32, torch.float64)
        and dirs.dtype == sh.dtype
    )


def sh_colors(
    sh: Tensor,  # [N, k, 3] the coefficients of the degree used, k = (degree + 1)^2
    dirs: Tensor,  # [N, 3] viewing directions, any length
) -> Tensor:  # [N, 3] max(SH(dirs / |dirs|) + 0.5, 0)
    """:func:`n2f2.render.sh.eval_sh_torch` compiled (differentiable in ``sh`` and ``dirs``)."""
    return _ShColors.apply(sh, dirs)
