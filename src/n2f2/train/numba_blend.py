"""The blend cache's row requests compiled with numba: :meth:`BlendCache.request_torch`'s CSR
matrices, array for array, in three loops instead of some twenty tensor operations.

A training step asks the cache for the rows of its ~2k sampled pixels (~75k entries on the demo
scene) and, for the backward, for their transpose. The torch request gathers the entries with
index arithmetic and builds the transpose with a stable argsort by Gaussian; here the rows are
copied in order and the transpose is a counting sort by Gaussian (stable, so each Gaussian lists
its pixels in ascending order): the same arrays at a fraction of the fixed cost per operation.
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
    def _request(crow_all, gid_all, weight_all, rows, n, transpose):
        """The rows ``rows`` of the cached CSR matrix (crow_all, gid_all, weight_all) as a CSR
        matrix [P, n], and with ``transpose`` that matrix's transpose [n, P] as CSR."""
        p = rows.shape[0]
        crow = np.empty(p + 1, dtype=np.int32)
        crow[0] = 0
        for r in range(p):
            crow[r + 1] = crow[r] + (crow_all[rows[r] + 1] - crow_all[rows[r]])
        nnz = crow[p]
        col = np.empty(nnz, dtype=np.int32)
        val = np.empty(nnz, dtype=np.float32)
        for r in range(p):
            src = crow_all[rows[r]]
            for e in range(crow[r], crow[r + 1]):
                col[e] = gid_all[src]
                val[e] = weight_all[src]
                src += 1
        if not transpose:
            return crow, col, val, np.zeros(1, dtype=np.int32), col[:0], val[:0]
        crow_t = np.zeros(n + 1, dtype=np.int32)
        for e in range(nnz):
            crow_t[col[e] + 1] += 1
        for g in range(n):
            crow_t[g + 1] += crow_t[g]
        fill = crow_t[:n].copy()
        col_t = np.empty(nnz, dtype=np.int32)
        val_t = np.empty(nnz, dtype=np.float32)
        for r in range(p):  # rows in ascending order: each Gaussian's pixels come out ascending
            for e in range(crow[r], crow[r + 1]):
                q = fill[col[e]]
                col_t[q] = r
                val_t[q] = val[e]
                fill[col[e]] = q + 1
        return crow, col, val, crow_t, col_t, val_t


def available() -> bool:
    return numba is not None


def warm_up() -> None:
    """Compile (or load from the cache) the request kernel, with the argument types a training
    step passes (:func:`n2f2.render.numba_runtime.compile_in_background` runs this)."""
    if numba is not None:
        crow = torch.tensor([0, 1, 2])
        request(crow, torch.tensor([0, 1], dtype=torch.int32), torch.ones(2), torch.tensor([1, 0]), 2, True)


def request(
    crow_all: Tensor,  # [R + 1] long, the cache's row pointers (CPU)
    gid_all: Tensor,  # [nnz] int32
    weight_all: Tensor,  # [nnz] float32
    rows: Tensor,  # [P] long, global pixel rows
    n: int,  # columns: the number of Gaussians
    transpose: bool,
) -> tuple[Tensor, Tensor, Tensor, Tensor | None, Tensor | None, Tensor | None]:
    """(crow [P + 1], col [E], value [E]) of the requested rows, int32 indices, and the same
    three arrays of the transpose [n, P] when ``transpose`` (else three Nones)."""
    out = _request(
        crow_all.numpy(),
        gid_all.numpy(),
        weight_all.numpy(),
        rows.numpy(),
        int(n),
        bool(transpose),
    )
    crow, col, val, crow_t, col_t, val_t = (torch.from_numpy(a) for a in out)
    if not transpose:
        return crow, col, val, None, None, None
    return crow, col, val, crow_t, col_t, val_t
