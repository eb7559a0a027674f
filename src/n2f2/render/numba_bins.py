"""Tile binning compiled with numba: :func:`n2f2.render.torch_backend.bin_gaussians`'s result,
bit for bit, in two loops instead of some forty tensor operations.

The torch binning builds the (tile, Gaussian) pairs with a depth sort, two repeat-interleaves
and a stable sort of the pairs by tile; at the demo's 12k Gaussians and 42k pairs its fixed
cost per operation is most of the time. Here the tile rectangle of each Gaussian comes from the
same float32 arithmetic, the Gaussians are taken in the same stable depth order, and a counting
sort by tile (stable, so depth order within a tile) writes the pairs: the same arrays.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from n2f2.render.torch_backend import Bins, bin_gaussians

try:  # optional at import time, as in the compositing kernels
    import numba
    from numba import njit
except ImportError:  # pragma: no cover - numba is a declared dependency
    numba = None

if numba is not None:

    @njit(cache=True, nogil=True)
    def _rectangles(mx, my, hx, hy, valid, width, height, row0, tile_size, rect):
        """rect [N, 4] int64: x0, y0, x1, y1 tile range of each Gaussian, x1 < x0 where it reaches
        no pixel centre (the torch binning's float32 arithmetic, step by step)."""
        half = np.float32(0.5)
        margin = np.float32(1e-3)
        top = np.float32(row0)
        last_col = np.float32(width - 1)
        last_row = top + np.float32(height - 1)
        for n in range(mx.shape[0]):
            # Pixel i has its centre at i + 0.5: covered ceil(m - h - .5) .. floor(m + h - .5).
            h = hx[n] + margin
            ax = max(np.float32(np.ceil(mx[n] - h - half)), np.float32(0.0))
            bx = min(np.float32(np.floor(mx[n] + h - half)), last_col)
            h = hy[n] + margin
            ay = max(np.float32(np.ceil(my[n] - h - half)), top) - top
            by = min(np.float32(np.floor(my[n] + h - half)), last_row) - top
            if valid[n] and ax <= bx and ay <= by:
                rect[n, 0] = int(ax) // tile_size
                rect[n, 1] = int(ay) // tile_size
                rect[n, 2] = int(bx) // tile_size
                rect[n, 3] = int(by) // tile_size
            else:
                rect[n, 0] = rect[n, 1] = 0
                rect[n, 2] = rect[n, 3] = -1

    @njit(cache=True, nogil=True)
    def _pairs(order, rect, tiles_x, n_tiles, pair_gid, pair_tile, tile_start, tile_len):
        """Write the pairs of the Gaussians in ``order`` (front to back), sorted by tile."""
        for q in range(order.shape[0]):
            x0, y0, x1, y1 = rect[order[q], 0], rect[order[q], 1], rect[order[q], 2], rect[order[q], 3]
            for ty in range(y0, y1 + 1):
                for tx in range(x0, x1 + 1):
                    tile_len[ty * tiles_x + tx] += 1
        s = 0
        for t in range(n_tiles):
            tile_start[t] = s
            s += tile_len[t]
        fill = tile_start.copy()
        for q in range(order.shape[0]):
            g = order[q]
            for ty in range(rect[g, 1], rect[g, 3] + 1):
                for tx in range(rect[g, 0], rect[g, 2] + 1):
                    t = ty * tiles_x + tx
                    pair_gid[fill[t]] = g
                    pair_tile[fill[t]] = t
                    fill[t] += 1


def usable(means2d: Tensor) -> bool:
    """Whether the compiled binning takes these inputs: float32 CPU tensors, numba present."""
    return numba is not None and means2d.device.type == "cpu" and means2d.dtype == torch.float32


@torch.no_grad()
def bin_gaussians_numba(
    means2d: Tensor,  # [N, 2] float32
    half_extent: Tensor,  # [2, N] float32
    depths: Tensor,  # [N] float32
    valid: Tensor,  # [N] bool
    width: int,
    height: int,
    tile_size: int = 8,
    row0: int = 0,  # bin only image rows [row0, row0 + height): one band of a taller image
) -> Bins:
    """:func:`~n2f2.render.torch_backend.bin_gaussians`, compiled for float32 CPU inputs (others go
    to it)."""
    if not usable(means2d):
        return bin_gaussians(means2d, half_extent, depths, valid, width, height, tile_size, row0)
    if row0 % tile_size:
        raise ValueError(f"a band must start on a tile row: row0 = {row0}, tile size {tile_size}")
    tiles_x = -(-width // tile_size)
    tiles_y = -(-height // tile_size)
    m = means2d.detach().numpy()
    h = half_extent.detach().numpy()
    N = m.shape[0]
    rect = np.empty((N, 4), dtype=np.int64)
    _rectangles(m[:, 0], m[:, 1], h[0], h[1], valid.numpy(), width, height, row0, tile_size, rect)
    ok = rect[:, 2] >= rect[:, 0]
    counts = (rect[:, 2] - rect[:, 0] + 1) * (rect[:, 3] - rect[:, 1] + 1) * ok
    # Depth order, stable (ties keep index order): the torch binning's radix sort of the depth
    # bits (positive floats order like their bit patterns).
    live = torch.from_numpy(np.flatnonzero(ok))
    key = depths.detach().index_select(0, live).view(torch.int32)
    order = live[torch.argsort(key, stable=True)].numpy()
    n_tiles = tiles_x * tiles_y
    total = int(counts.sum())
    pair_gid = np.empty(total, dtype=np.int64)
    pair_tile = np.empty(total, dtype=np.int64)
    tile_start = np.empty(n_tiles, dtype=np.int64)
    tile_len = np.zeros(n_tiles, dtype=np.int64)
    _pairs(order, rect, tiles_x, n_tiles, pair_gid, pair_tile, tile_start, tile_len)
    radii = torch.where(torch.from_numpy(ok), torch.ceil(half_extent.amax(0)), 0.0).to(torch.int32)
    return Bins(
        torch.from_numpy(pair_gid),
        torch.from_numpy(pair_tile),
        torch.from_numpy(tile_start),
        torch.from_numpy(tile_len),
        tiles_x,
        tiles_y,
        tile_size,
        radii,
        row0=row0,
    )
