"""The loss's per-row prefix sums compiled with numba (:func:`n2f2.train.losses.prefix_projected_loss`).

A training row r (a pixel and one segment covering it) needs two sums over the first ``M_r``
feature dims of its pixel: ``x G x`` (a prefix sum of the pixel's ``a_k``) and ``u . x`` (a
prefix dot product of the segment's ``u = W^T t`` with the pixel's theta). In tensor operations
each is a full cumulative sum over an ``[R, D]`` or ``[P, D]`` tensor of which one entry per row
is kept, and autograd walks back through the cumulative sums, the gathers and the products: on
the demo's 5k rows x 128 dims, some fifteen passes of 2.7 MB each way. Here each row reads only
its ``M_r`` entries forward, and the backward adds each row's share into the two gradients in one
pass (serially, in row order: the same sums whatever the thread count). The tensor expressions
stay the reference (tests compare both).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

try:  # optional at import time, as in the rasterizer's kernels
    import numba
    from numba import njit
except ImportError:  # pragma: no cover - numba is a declared dependency
    numba = None

if numba is not None:

    @njit(cache=True, nogil=True)
    def _dot_forward(u, theta, index, row, last, out):
        for r in range(row.shape[0]):
            j, p = index[r], row[r]
            s = 0.0
            for k in range(last[r] + 1):
                s += np.float64(u[j, k]) * np.float64(theta[p, k])
            out[r] = s

    @njit(cache=True, nogil=True)
    def _dot_backward(u, theta, index, row, last, grad, g_u, g_theta):
        for r in range(row.shape[0]):
            j, p = index[r], row[r]
            gr = np.float64(grad[r])
            for k in range(last[r] + 1):
                g_u[j, k] += gr * theta[p, k]
                g_theta[p, k] += gr * u[j, k]

    @njit(cache=True, nogil=True)
    def _sum_forward(a, row, last, out):
        for r in range(row.shape[0]):
            p = row[r]
            s = 0.0
            for k in range(last[r] + 1):
                s += np.float64(a[p, k])
            out[r] = s

    @njit(cache=True, nogil=True)
    def _sum_backward(row, last, grad, g_a):
        """g_a [P, D] (zeroed): each row's gradient at its last dim, then summed from the right."""
        for r in range(row.shape[0]):
            g_a[row[r], last[r]] += grad[r]
        for p in range(g_a.shape[0]):
            s = 0.0
            for k in range(g_a.shape[1] - 1, -1, -1):
                s += g_a[p, k]
                g_a[p, k] = s


def _arrays(*tensors: Tensor) -> list[np.ndarray]:
    return [t.detach().contiguous().numpy() for t in tensors]


class _PrefixDot(torch.autograd.Function):
    @staticmethod
    def forward(ctx, u, theta, index, row, last):
        u_np, th_np, index_np, row_np, last_np = _arrays(u, theta, index, row, last)
        out = np.empty(row_np.shape[0], np.float64)
        _dot_forward(u_np, th_np, index_np, row_np, last_np, out)
        ctx.saved = (u_np, th_np, index_np, row_np, last_np)
        return torch.from_numpy(out.astype(th_np.dtype))

    @staticmethod
    def backward(ctx, grad):
        u_np, th_np, index_np, row_np, last_np = ctx.saved
        g_u, g_theta = np.zeros(u_np.shape), np.zeros(th_np.shape)
        (grad_np,) = _arrays(grad.to(torch.float64))
        _dot_backward(u_np, th_np, index_np, row_np, last_np, grad_np, g_u, g_theta)
        dtype = th_np.dtype
        return torch.from_numpy(g_u.astype(dtype)), torch.from_numpy(g_theta.astype(dtype)), None, None, None


class _PrefixSum(torch.autograd.Function):
    @staticmethod
    def forward(ctx, a, row, last):
        a_np, row_np, last_np = _arrays(a, row, last)
        out = np.empty(row_np.shape[0], np.float64)
        _sum_forward(a_np, row_np, last_np, out)
        ctx.saved = (a_np.shape, a_np.dtype, row_np, last_np)
        return torch.from_numpy(out.astype(a_np.dtype))

    @staticmethod
    def backward(ctx, grad):
        shape, dtype, row_np, last_np = ctx.saved
        g_a = np.zeros(shape)
        (grad_np,) = _arrays(grad.to(torch.float64))
        _sum_backward(row_np, last_np, grad_np, g_a)
        return torch.from_numpy(g_a.astype(dtype)), None, None


def available() -> bool:
    return numba is not None


def usable(*tensors: Tensor) -> bool:
    """Whether the compiled sums take these tensors: CPU float tensors, numba present."""
    return numba is not None and all(
        t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64) for t in tensors
    )


def prefix_dot(
    u: Tensor,  # [T, D]
    theta: Tensor,  # [P, D]
    index: Tensor,  # [R] long, each row's row of u
    row: Tensor,  # [R] long, each row's row of theta
    last: Tensor,  # [R] long in [0, D), each row's last summed dim
) -> Tensor:  # [R]: sum_{k <= last_r} u[index_r, k] theta[row_r, k], differentiable in u and theta
    if not usable(u, theta):
        tx = torch.cumsum(u.index_select(0, index) * theta.index_select(0, row), 1)
        return tx.reshape(-1).index_select(0, torch.arange(len(row), device=row.device) * u.shape[1] + last)
    return _PrefixDot.apply(u, theta.to(u.dtype), index, row, last)


def prefix_sum(
    a: Tensor,  # [P, D]
    row: Tensor,  # [R] long, each row's row of a
    last: Tensor,  # [R] long in [0, D), each row's last summed dim
) -> Tensor:  # [R]: sum_{k <= last_r} a[row_r, k], differentiable in a
    if not usable(a):
        return torch.cumsum(a, 1).reshape(-1).index_select(0, row * a.shape[1] + last)
    return _PrefixSum.apply(a, row, last)


def warm_up() -> None:
    """Compile (or load from the cache) the four kernels with a training step's argument types
    (:func:`n2f2.render.numba_runtime.compile_in_background` runs this)."""
    if numba is not None:
        theta = torch.ones(2, 3, requires_grad=True)
        u = torch.ones(1, 3, requires_grad=True)
        row, last = torch.tensor([0, 1]), torch.tensor([2, 0])
        (prefix_dot(u, theta, torch.tensor([0, 0]), row, last) + prefix_sum(theta, row, last)).sum().backward()
