"""Cached alpha-blending weights of the frozen Gaussians (a CPU speed-up of deferred rendering).

While the feature field trains, the 3DGS is frozen, so for every view the rasterizer is a fixed
*linear* map from per-Gaussian features to pixels: ``F(p) = sum_i w_{p,i} f_i`` with
``w_{p,i} = alpha_i(p) T_i(p)``. On CPU that map costs ~75% of a training step when it is
recomputed by rasterizing every step (forward + backward). Here it is computed once per view
as a sparse matrix (pixel -> (Gaussian, weight) entries; ~30 per pixel on the demo scene), and a
step only gathers the entries of its sampled pixels. The result is the rasterizer's output,
not an approximation (checked against :func:`n2f2.render.rasterize` in the tests), and
gradients reach the per-Gaussian features exactly as through the rasterizer.

The weights are computed with the pure-PyTorch backend's own projection, binning and chunk
compositing (:mod:`n2f2.render.torch_backend`), so they follow the same 3DGS rules (alpha clamp,
alpha_min, early termination) by construction.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Optional, Sequence

import torch
from torch import Tensor

from ..sparse import constant_sparse_matmul, csr_matrix

if TYPE_CHECKING:
    from ..cameras import Camera


@dataclass
class BlendCache:
    """Sparse blending weights of several views, rows = global pixels (``offsets[k] + p`` for
    flat pixel p of the k-th cached view), in CSR form."""

    crow: Tensor  # [R + 1] long: entries of global pixel r are crow[r]:crow[r + 1]
    gid: Tensor  # [nnz] int32 Gaussian index
    weight: Tensor  # [nnz] float32 blending weight alpha_i T_i
    offsets: list[int]  # first global pixel of each cached view
    sizes: list[tuple[int, int]]  # (height, width) of each cached view

    @property
    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in (self.crow, self.gid, self.weight))

    def blend(
        self,
        features: Tensor,  # [N, C] per-Gaussian features
        slot: Tensor,  # [P] long, index of the cached view
        pixel: Tensor,  # [P] long, flat pixel index in that view
    ) -> Tensor:  # [P, C] rendered features at those pixels
        """What rasterizing ``features`` gives at the requested pixels (differentiable in
        ``features``)."""
        # The requested rows as a CSR matrix [P, N]: one sparse-dense product forward, its
        # transpose backward (~1.3x faster than embedding_bag, ~3x than index_select + index_add).
        # The transpose is built only when a backward will need it.
        transpose = features.requires_grad and torch.is_grad_enabled()
        matrix, transposed = self.request(slot, pixel, features.shape[0], transpose)
        return constant_sparse_matmul(matrix, features, transposed)

    def request(
        self,
        slot: Tensor,  # [P] long, index of the cached view
        pixel: Tensor,  # [P] long, flat pixel index in that view
        n: int,  # the number of Gaussians (columns)
        transpose: bool,
    ) -> tuple[Tensor, Optional[Tensor]]:  # sparse CSR [P, n], and its transpose [n, P] or None
        """The requested pixels' rows of the cache, and their transpose when ``transpose``:
        compiled on CPU (:mod:`n2f2.train.numba_blend`, the same arrays), else
        :meth:`request_torch`."""
        from . import numba_blend

        if not (numba_blend.available() and self.crow.device.type == "cpu"):
            return self.request_torch(slot, pixel, n, transpose)
        rows = torch.as_tensor(self.offsets, dtype=torch.long)[slot] + pixel  # [P] global pixel
        crow, col, val, crow_t, col_t, val_t = numba_blend.request(self.crow, self.gid, self.weight, rows, n, transpose)
        matrix = csr_matrix(crow, col, val, (rows.shape[0], n))
        if crow_t is None or col_t is None or val_t is None:
            return matrix, None
        return matrix, csr_matrix(crow_t, col_t, val_t, (n, rows.shape[0]))

    def request_torch(
        self,
        slot: Tensor,  # [P] long, index of the cached view
        pixel: Tensor,  # [P] long, flat pixel index in that view
        n: int,  # the number of Gaussians (columns)
        transpose: bool,
    ) -> tuple[Tensor, Optional[Tensor]]:  # sparse CSR [P, n], and its transpose [n, P] or None
        """:meth:`request` in tensor operations (any device; the reference of the compiled one)."""
        offsets = torch.as_tensor(self.offsets, dtype=torch.long, device=pixel.device)
        rows = offsets[slot] + pixel  # [P] global pixel
        start, count = self.crow[rows], self.crow[rows + 1] - self.crow[rows]
        owner = torch.repeat_interleave(torch.arange(rows.shape[0], device=rows.device), count)  # [E]
        crow = torch.cat([count.new_zeros(1), torch.cumsum(count, 0)])  # [P + 1] row pointers of the request
        entry = start[owner] + torch.arange(owner.shape[0], device=rows.device) - crow[:-1][owner]  # [E]
        # gid stays int32: csr_matrix keeps int32 indices.
        gid, weight = self.gid.index_select(0, entry), self.weight.index_select(0, entry)
        shape = (rows.shape[0], n)
        matrix = csr_matrix(crow, gid, weight, shape)
        if not transpose:
            return matrix, None
        # The transpose as CSR for the backward, from the entries stably sorted by Gaussian
        # (each row then lists its pixels in ascending order, as torch's conversion does): the
        # product with the transposed (CSC) view converted it on every step, at about twice the
        # cost of this sort.
        order = torch.argsort(gid, stable=True)
        crow_t = torch.zeros(n + 1, dtype=torch.long, device=gid.device)
        torch.cumsum(torch.bincount(gid, minlength=n), 0, out=crow_t[1:])
        transposed = csr_matrix(crow_t, owner.index_select(0, order), weight.index_select(0, order), (n, shape[0]))
        return matrix, transposed


@torch.no_grad()
def view_blend_weights(
    geometry: dict[str, Tensor],  # means [N,3], quats [N,4], scales [N,3], opacities [N]
    camera: Camera,
) -> tuple[Tensor, Tensor, Tensor]:  # pixel [nnz] long, gid [nnz] long, weight [nnz]
    """Every non-zero (pixel, Gaussian, weight) of one view, with the torch backend's defaults
    (tile 8, alpha clamp 0.99, alpha_min 1/255, transmittance_min 1e-4, eps2d 0.3). The
    projection, binning and pair coefficients are the CPU renderer's (compiled where numba runs,
    which fall back to the torch ones elsewhere), so that the weights are those the renderer
    blends with: a projection rounded differently moves pairs across the alpha and transmittance
    cut-offs."""
    from ..render import torch_backend as tb
    from ..render.numba_backend import compiled_steps

    steps = compiled_steps()
    W, H = camera.width, camera.height
    cam = camera.to_torch(device=geometry["means"].device, dtype=geometry["means"].dtype)
    proj = steps["project"](
        geometry["means"], geometry["quats"], geometry["scales"], geometry["opacities"], cam["viewmat"], cam["K"], W, H
    )
    ts = 8
    bins = steps["binning"](proj.means2d, proj.half_extent, proj.depths, proj.valid, W, H, ts)
    kp = steps["coefficients"](proj.means2d, proj.conics, geometry["opacities"], bins)
    cfg = tb.CompositeConfig()
    P = tb._pixel_basis(ts, kp.dtype, kp.device)
    th = tb._thresholds(cfg, kp.dtype)
    pix, gid, wt = [], [], []
    for tiles in tb._Schedule(bins, cfg).batches:
        pos, pad, lens = tb._gather_batch(kp, bins, tiles)
        kb = tb._padded_coefficients(kp, pos, pad)  # [B, 6, L]
        gb = bins.pair_gid[pos]  # [B, L]
        T = torch.ones(tiles.shape[0], ts * ts, dtype=kp.dtype, device=kp.device)
        for c0 in range(0, kb.shape[2], cfg.chunk):
            w, T_next, _ = tb._chunk(kb[:, :, c0 : c0 + cfg.chunk], P, T, th)  # [B, p, k]
            # Flat indices: advanced indexing with three index tensors is ~10x slower on CPU.
            kk = w.shape[2]
            flat = torch.nonzero(w.reshape(-1)).squeeze(1)
            b, rem = flat.div(ts * ts * kk, rounding_mode="floor"), flat % (ts * ts * kk)
            p, k = rem.div(kk, rounding_mode="floor"), rem % kk
            tile = tiles.index_select(0, b)
            row = (tile // bins.tiles_x) * ts + p // ts
            col = (tile % bins.tiles_x) * ts + p % ts
            inside = torch.nonzero((row < H) & (col < W)).squeeze(1)  # edge tiles overhang the image
            pix.append((row * W + col).index_select(0, inside))
            gid.append(gb[:, c0 : c0 + kk].reshape(-1).index_select(0, (b * kk + k).index_select(0, inside)))
            wt.append(w.reshape(-1).index_select(0, flat.index_select(0, inside)))
            T = T_next[:, :, -1]
            if bool((T.amax(1) == 0).all()):  # every pixel of the batch has stopped
                break
    if not pix:
        z = torch.zeros(0, dtype=torch.long, device=kp.device)
        return z, z, torch.zeros(0, dtype=kp.dtype, device=kp.device)
    return torch.cat(pix), torch.cat(gid), torch.cat(wt)


def build_blend_cache(
    geometry: dict[str, Tensor], cameras: Sequence[Any], *, max_bytes: float = float("inf"), progress: bool = False
) -> BlendCache:
    """Blending weights of ``cameras`` (one cached view each). Raises MemoryError as soon as the
    projected size (bytes so far / views done x views) exceeds ``max_bytes``."""
    from tqdm import tqdm

    crows, gids, weights, offsets, sizes = [], [], [], [], []
    total_rows, total_nnz, nbytes = 0, 0, 0
    # The bar opens once the first view's projection fits in max_bytes: a cache that does not
    # fit (most real scenes at the default limit) is given up after one view, and a bar opened
    # before it would be left at 0% (in a log, for good). Closed however the loop ends.
    bar = None
    try:
        for k, cam in enumerate(cameras):
            pix, gid, wt = view_blend_weights(geometry, cam)
            order = torch.argsort(pix, stable=True)
            counts = torch.bincount(pix, minlength=cam.width * cam.height)
            crows.append(torch.cumsum(counts, 0) + total_nnz)
            gids.append(gid[order].to(torch.int32))
            weights.append(wt[order].float())
            offsets.append(total_rows)
            sizes.append((cam.height, cam.width))
            total_rows += cam.width * cam.height
            total_nnz += int(pix.numel())
            nbytes += int(pix.numel()) * 8 + cam.width * cam.height * 8
            if nbytes / (k + 1) * len(cameras) > max_bytes:
                raise MemoryError(
                    f"blend-weight cache would need ~{nbytes / (k + 1) * len(cameras) / 2**20:.0f} MB "
                    f"(limit {max_bytes / 2**20:.0f} MB)"
                )
            if bar is None:  # starts at the view just done (its rate counts the views after it)
                bar = tqdm(
                    total=len(cameras), initial=1, desc="blend weights", unit="view", disable=not progress, leave=False
                )
            else:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    device = geometry["means"].device
    crow = (
        torch.cat([torch.zeros(1, dtype=torch.long, device=device)] + crows)
        if crows
        else torch.zeros(1, dtype=torch.long, device=device)
    )
    return BlendCache(
        crow=crow,
        gid=torch.cat(gids) if gids else torch.zeros(0, dtype=torch.int32),
        weight=torch.cat(weights) if weights else torch.zeros(0),
        offsets=offsets,
        sizes=sizes,
    )
