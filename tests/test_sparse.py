"""Products with constant sparse matrices (n2f2.sparse): values and gradients against dense."""

from __future__ import annotations

import pytest
import torch

from n2f2.sparse import constant_sparse_matmul, csr_matrix, sparse_dense, transpose_csr


def _random_csr(rows: int, cols: int, per_row: list[int], dtype=torch.float64, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    col = torch.cat([torch.randperm(cols, generator=g)[:k].sort().values for k in per_row])
    crow = torch.cat([torch.zeros(1, dtype=torch.long), torch.cumsum(torch.tensor(per_row), 0)])
    value = torch.randn(col.shape[0], generator=g, dtype=dtype)
    return csr_matrix(crow, col, value, (rows, cols))


@pytest.mark.parametrize("precomputed", [False, True])
def test_constant_sparse_matmul_matches_dense_with_gradients(precomputed):
    a = _random_csr(6, 9, [3, 0, 9, 1, 4, 0])  # empty rows and a full row
    x = torch.randn(9, 5, dtype=torch.float64, requires_grad=True)
    up = torch.randn(6, 5, dtype=torch.float64)
    out = constant_sparse_matmul(a, x, transpose_csr(a) if precomputed else None)
    (grad,) = torch.autograd.grad((out * up).sum(), x)
    dense = a.to_dense()
    torch.testing.assert_close(out, dense @ x)
    torch.testing.assert_close(grad, dense.t() @ up)


def test_transpose_csr_is_the_transpose():
    a = _random_csr(5, 7, [2, 7, 0, 1, 3])
    torch.testing.assert_close(transpose_csr(a).to_dense(), a.to_dense().t())


def test_dtype_follows_the_dense_operand_and_layout_is_checked():
    a = _random_csr(3, 4, [2, 1, 4], dtype=torch.float32)
    x = torch.randn(4, 2, dtype=torch.float64, requires_grad=True)
    out = constant_sparse_matmul(a, x)
    assert out.dtype == torch.float64
    torch.testing.assert_close(out, a.to_dense().double() @ x)
    with pytest.raises(ValueError, match="CSR"):
        constant_sparse_matmul(a.to_dense(), x)


def test_sparse_dense_overwrites_its_output_rows_without_entries_included():
    # The fast path writes the product into ``out`` with beta = 0, never reading it: rows of
    # ``a`` without entries must come out 0, not the NaN that was there.
    a = _random_csr(6, 9, [3, 0, 9, 1, 4, 0])
    x = torch.randn(9, 5, dtype=torch.float64)
    out = torch.full((6, 5), float("nan"), dtype=torch.float64)
    result = sparse_dense(a, x, out=out)
    assert result.data_ptr() == out.data_ptr()
    torch.testing.assert_close(result, a.to_dense() @ x)
    assert (result[1] == 0).all() and (result[5] == 0).all()
