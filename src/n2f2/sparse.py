"""Products with constant sparse matrices, differentiable in the dense operand.

Two training-time maps are fixed linear maps: the TriPlane's bilinear taps of the frozen
Gaussian centres (texels -> Gaussians) and the cached blending weights of the frozen Gaussians
(Gaussians -> pixels). As CSR matrices, their forward is one sparse-dense product, and the
backward is the product with the transpose, a row gather too: no scatter, no sort. On the
2-core CPU that is ~1.9x faster than gather + index_add for the TriPlane and ~1.3x faster than
``embedding_bag`` for the blend (benchmarked on the demo scene, forward + backward).
"""

from __future__ import annotations

import warnings
from typing import Optional

import torch
from torch import Tensor

_INT32_LIMIT = 2**31 - 1  # indices and entry counts below this fit int32


def csr_matrix(
    crow: Tensor,  # [R + 1] long row pointers
    col: Tensor,  # [nnz] long column of each entry
    value: Tensor,  # [nnz] float
    shape: tuple[int, int],
) -> Tensor:  # sparse CSR [R, K]
    """A CSR tensor, without the beta-feature warning torch prints for every new layout.

    Its indices are int32 where they fit: the CPU sparse-dense product converts int64 indices
    to int32 on every call (two copies of the index arrays per product)."""
    if max(shape[0], shape[1], col.numel()) < _INT32_LIMIT:
        crow, col = crow.to(torch.int32), col.to(torch.int32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(crow, col, value, shape)


def transpose_csr(a: Tensor) -> Tensor:  # sparse CSR [R, K] -> sparse CSR [K, R]
    """The transpose as a CSR matrix of its own (worth it for a matrix used many times)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return a.t().to_sparse_csr()


def sparse_dense(
    a: Tensor,  # sparse [R, K]
    x: Tensor,  # [K, C]
    out: Optional[Tensor] = None,  # [R, C] written (its values are never read); None: a new tensor
) -> Tensor:  # [R, C] = a @ x
    """``a @ x``. On CPU, ``a @ x`` with a sparse CSR ``a`` fills a zero tensor of the result's
    size and copies it into the result before the product overwrites it: two passes over memory
    that, in a training step, cost more than the product (the TriPlane's texel gradient is 6 MB).
    ``addmm`` with ``beta = 0`` into its own ``out`` skips both; torch documents that ``beta = 0``
    ignores the input's values (not even NaN propagates), so an uninitialised ``out`` is fine."""
    if a.device.type != "cpu" or a.layout != torch.sparse_csr:
        return a @ x if out is None else out.copy_(a @ x)
    if out is None:
        out = x.new_empty(a.shape[0], x.shape[1])
    return torch.addmm(out, a, x, beta=0.0, alpha=1.0, out=out)


class _ConstantSparseMatmul(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, a: Tensor, a_t: Optional[Tensor]) -> Tensor:
        ctx.a, ctx.a_t = a, a_t
        return sparse_dense(a, x)

    @staticmethod
    def backward(ctx, grad: Tensor):
        a_t = ctx.a_t if ctx.a_t is not None else ctx.a.t()  # a CSC view: no copy
        return sparse_dense(a_t, grad), None, None


def constant_sparse_matmul(
    a: Tensor,  # sparse CSR [R, K], constant (no gradient)
    x: Tensor,  # [K, C]
    a_t: Optional[Tensor] = None,  # CSR [K, R] = a^T when precomputed
) -> Tensor:  # [R, C] = a @ x, differentiable in x
    """``a @ x`` whose backward is ``a^T @ grad`` (``a_t``, or transposed on demand)."""
    if a.layout != torch.sparse_csr:
        raise ValueError(f"constant_sparse_matmul needs a CSR matrix, got layout {a.layout}")
    if a.dtype != x.dtype:
        a = a.to(x.dtype)
        a_t = None if a_t is None else a_t.to(x.dtype)
    return _ConstantSparseMatmul.apply(x, a, a_t)
