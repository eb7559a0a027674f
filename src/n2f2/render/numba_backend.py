"""Tile compositing compiled with numba: the CPU fast path of the rasterizer.

Projection, binning and the per-pair ``log2 alpha`` polynomial are the torch backend's
(:mod:`n2f2.render.torch_backend`, plain autograd); only the compositing, the loop over
pixel-Gaussian pairs, runs here, as two compiled kernels that follow 3DGS's CUDA ones:

* forward: per pixel, walk the tile's depth-sorted list front to back, blend, stop at the
  transmittance limit, and record how many pairs the pixel walked (``stop``);
* backward: per pixel, walk the same pairs front to back again with the same arithmetic,
  carrying the prefix sum ``sum_{j<=i} w_j f_j . g`` so that no division by ``1 - alpha``
  reconstructs a transmittance (the torch backend's formula, written per pair).

Both walk a tile's list one Gaussian at a time: a branch-free pass over the tile's pixels
evaluates ``log2 alpha`` and collects the pixels above ``alpha_min`` (about a quarter of the
pairs walked in a 3DGS-like scene), and only those are blended. The loops over the D channels
are the cost for large C; the backward does them four pixels at a time. Dense per-tile
products through BLAS (``[p, len] @ [len, D]``) do four times the multiply-adds at that
sparsity and measured slower at C = 64 (a [64, 128] @ [128, 66] float32 product alone took
2.4-3.6 ns per pixel-pair on one core, about the whole sparse blend's cost).

Tiles are dealt to threads round-robin in order of list length, longest first. Per-pair
gradients are written by the one thread that owns the tile (no race); per-Gaussian feature
gradients go to one buffer per thread, summed at the end.

numba ships its compiler in its wheel, so nothing is built at install time. Kernels are
compiled on first use (a few seconds) and cached on disk beside this file, or in numba's
user cache when that folder is read-only. Calls are serialised by a lock: the thread pool
used here does not allow two Python threads inside a parallel region at once.

torch's OpenMP threads must not spin-wait through these kernels (with OpenMP's default spin
count a render took 25x longer on 2 cores): the ``n2f2`` command sets ``GOMP_SPINCOUNT`` (see
:mod:`n2f2.cli`); library users on few cores set it, or ``OMP_WAIT_POLICY=PASSIVE``, before
importing torch.
"""

from __future__ import annotations

import math
import os
import threading

import numpy as np
import torch
from torch import Tensor

from n2f2.render.torch_backend import Bins, CompositeConfig, rasterize_torch

try:  # optional at import time: the "auto" backend falls back to torch without it
    import numba
    from numba import njit, prange
    from numba.core import config as numba_config
except ImportError:  # pragma: no cover - numba is a declared dependency
    numba = None
else:
    # numba's OpenMP layer leaves its threads spinning after each kernel, which slows the torch
    # operations around it several times over; the plain thread pool does not spin.
    if "NUMBA_THREADING_LAYER" not in os.environ:
        # numba fills its config module from the environment at import time, so stubs lack the names.
        numba_config.THREADING_LAYER = "workqueue"  # pyright: ignore[reportAttributeAccessIssue]

_LOCK = threading.Lock()
_LN2 = math.log(2.0)
# Reassociation lets the loops over channels vectorise; no flag that assumes finite values.
_FAST = {"reassoc", "contract", "nsz", "arcp"}


def numba_usable() -> bool:
    """True when the kernels can run here (numba imports)."""
    return numba is not None


# Gaussians per step of a tile's list: their feature rows are gathered into a per-thread
# buffer first (independent loads that overlap, instead of one cache miss per Gaussian), and
# the backward's per-Gaussian feature gradients are summed there before one scatter per step.
_CHUNK = 64

if numba is not None:

    @njit(parallel=True, fastmath=_FAST, cache=True, nogil=True)
    def _forward_kernel(
        kp,  # [M, 6] log2 alpha polynomial of each pair, relative to its tile's centre
        gid,  # [M] int64 Gaussian of each pair
        tile_start,  # [T] int64
        tile_len,  # [T] int64
        order,  # [T'] int64 non-empty tiles, longest list first
        aug,  # [N, D] features, z, 1
        basis,  # [5, p] u, v, u^2, uv, v^2 of each pixel (offsets from the tile centre)
        log_min,
        log_clamp,
        t_min,  # thresholds (log2 alpha_min, log2 alpha_clamp, transmittance)
        nthreads,
        out,  # [T, p, D] zero-initialised
        stop,  # [T, p] int64: pairs walked by each pixel
    ):
        P = basis.shape[1]
        D = aug.shape[1]
        one = t_min / t_min  # 1 in the arrays' type (a float literal would turn float32 maths into float64)
        for t in prange(nthreads):
            T = np.empty(P, dtype=out.dtype)
            lim = np.empty(P, dtype=out.dtype)  # log2 alpha_min while the pixel is live, +inf once it stopped
            la = np.empty(P, dtype=out.dtype)  # log2 alpha of the current Gaussian at each pixel
            hit = np.empty(P, dtype=np.int64)  # pixels the current Gaussian reaches
            A = np.empty((_CHUNK, D), dtype=out.dtype)  # feature rows of the current step
            for ii in range(t, order.shape[0], nthreads):
                tile = order[ii]
                s = tile_start[tile]
                n = tile_len[tile]
                T[:] = 1.0
                lim[:] = log_min
                stop[tile, :] = n
                n_live = P
                acc = out[tile]
                for j in range(n):
                    q = s + j
                    jc = j % _CHUNK
                    if jc == 0:
                        for i in range(min(_CHUNK, n - j)):
                            A[i, :] = aug[gid[q + i]]
                    k0, k1, k2, k3, k4, k5 = kp[q, 0], kp[q, 1], kp[q, 2], kp[q, 3], kp[q, 4], kp[q, 5]
                    # Branch-free passes over all pixels (most of a Gaussian's pixels in its tiles
                    # fall below alpha_min), then the blending only where it counts.
                    for p in range(P):
                        la[p] = (
                            k0
                            + k1 * basis[0, p]
                            + k2 * basis[1, p]
                            + k3 * basis[2, p]
                            + k4 * basis[3, p]
                            + k5 * basis[4, p]
                        )
                    c = 0
                    for p in range(P):
                        hit[c] = p
                        c += la[p] >= lim[p]
                    a = A[jc]
                    for i in range(c):
                        p = hit[i]
                        alpha = np.exp2(min(la[p], log_clamp))
                        T_next = T[p] * (one - alpha)
                        if T_next < t_min:  # this Gaussian is not blended and the pixel stops
                            lim[p] = np.inf
                            stop[tile, p] = j
                            n_live -= 1
                            continue
                        w = alpha * T[p]
                        row = acc[p]
                        for d in range(D):
                            row[d] += w * a[d]
                        T[p] = T_next
                    if n_live == 0:
                        break

    @njit(parallel=True, fastmath=_FAST, cache=True, nogil=True)
    def _backward_kernel(
        kp,  # [M, 6]
        gid,  # [M] int64
        tile_start,  # [T]
        order,  # [T']
        aug,  # [N, D]
        basis,  # [5, p]
        log_min,
        log_clamp,
        ln2,  # ln2: log(2) in the arrays' type
        nthreads,
        out,  # [T, p, D] forward output
        g_out,  # [T, D, p] upstream gradient (the torch backend's layout)
        stop,  # [T, p] from the forward pass
        g_kp,  # [M, 6] zero-initialised
        g_aug,  # [nthreads, N, D] zero-initialised
    ):
        # O = sum_i w_i f_i, w_i = alpha_i T_i:  dL/dalpha_i = (T_{i+1} fg_i - total + prefix_i) / (1 - alpha_i)
        # with fg_i = f_i . g, total = O . g and prefix_i = sum_{j<=i} w_j fg_j.
        P = basis.shape[1]
        D = aug.shape[1]
        one = ln2 / ln2  # typed 1 and 0, as in the forward
        zero = one - one
        for t in prange(nthreads):
            T = np.empty(P, dtype=out.dtype)
            base = np.empty(P, dtype=out.dtype)  # prefix - total
            la = np.empty(P, dtype=out.dtype)
            hit = np.empty(P, dtype=np.int64)
            wv = np.empty(P, dtype=out.dtype)  # per reached pixel: w, alpha, f . g
            av = np.empty(P, dtype=out.dtype)
            fv = np.empty(P, dtype=out.dtype)
            A = np.empty((_CHUNK, D), dtype=out.dtype)  # feature rows of the step
            GA = np.empty((_CHUNK, D), dtype=out.dtype)  # their gradients, scattered after the step
            G = np.empty((P, D), dtype=out.dtype)  # the tile's upstream gradient, one row per pixel
            for ii in range(t, order.shape[0], nthreads):
                tile = order[ii]
                s = tile_start[tile]
                Gt = g_out[tile]
                for d in range(D):
                    for p in range(P):
                        G[p, d] = Gt[d, p]
                O = out[tile]
                st = stop[tile]
                walked = 0
                for p in range(P):
                    tot = zero
                    Op = O[p]
                    Gp = G[p]
                    for d in range(D):
                        tot += Op[d] * Gp[d]
                    base[p] = -tot
                    T[p] = 1.0
                    walked = max(walked, st[p])
                for j0 in range(0, walked, _CHUNK):
                    m = min(_CHUNK, walked - j0)
                    for i in range(m):
                        A[i, :] = aug[gid[s + j0 + i]]
                    GA[:m, :] = 0.0
                    for jc in range(m):
                        j = j0 + jc
                        q = s + j
                        k0, k1, k2, k3, k4, k5 = kp[q, 0], kp[q, 1], kp[q, 2], kp[q, 3], kp[q, 4], kp[q, 5]
                        for p in range(P):
                            la[p] = (
                                k0
                                + k1 * basis[0, p]
                                + k2 * basis[1, p]
                                + k3 * basis[2, p]
                                + k4 * basis[3, p]
                                + k5 * basis[4, p]
                            )
                        c = 0
                        for p in range(P):
                            hit[c] = p
                            c += (la[p] >= log_min) & (j < st[p])
                        if c == 0:
                            continue
                        a = A[jc]
                        gacc = GA[jc]
                        for i in range(c):
                            p = hit[i]
                            alpha = np.exp2(min(la[p], log_clamp))
                            wv[i] = alpha * T[p]
                            av[i] = alpha
                            T[p] = T[p] * (one - alpha)  # now T_{i+1}
                        # f . g and the feature gradient, four pixels per pass over the channels:
                        # one load and store of the gradient row per four products.
                        i = 0
                        while i + 4 <= c:
                            G0, G1, G2, G3 = G[hit[i]], G[hit[i + 1]], G[hit[i + 2]], G[hit[i + 3]]
                            w0, w1, w2, w3 = wv[i], wv[i + 1], wv[i + 2], wv[i + 3]
                            f0 = f1 = f2 = f3 = zero
                            for d in range(D):
                                ad = a[d]
                                x0, x1, x2, x3 = G0[d], G1[d], G2[d], G3[d]
                                f0 += ad * x0
                                f1 += ad * x1
                                f2 += ad * x2
                                f3 += ad * x3
                                gacc[d] += w0 * x0 + w1 * x1 + w2 * x2 + w3 * x3
                            fv[i], fv[i + 1], fv[i + 2], fv[i + 3] = f0, f1, f2, f3
                            i += 4
                        while i < c:
                            Gp = G[hit[i]]
                            w = wv[i]
                            f = zero
                            for d in range(D):
                                gd = Gp[d]
                                f += a[d] * gd
                                gacc[d] += w * gd
                            fv[i] = f
                            i += 1
                        g0 = g1 = g2 = g3 = g4 = g5 = zero
                        for i in range(c):
                            p = hit[i]
                            fg = fv[i]
                            base[p] += wv[i] * fg
                            if la[p] <= log_clamp:  # a clamped alpha passes no gradient
                                alpha = av[i]
                                d_la = (T[p] * fg + base[p]) / (one - alpha) * alpha * ln2
                                g0 += d_la
                                g1 += d_la * basis[0, p]
                                g2 += d_la * basis[1, p]
                                g3 += d_la * basis[2, p]
                                g4 += d_la * basis[3, p]
                                g5 += d_la * basis[4, p]
                        g_kp[q, 0] = g0
                        g_kp[q, 1] = g1
                        g_kp[q, 2] = g2
                        g_kp[q, 3] = g3
                        g_kp[q, 4] = g4
                        g_kp[q, 5] = g5
                    for i in range(m):
                        ga = g_aug[t, gid[s + j0 + i]]
                        gs = GA[i]
                        for d in range(D):
                            ga[d] += gs[d]


def _pixel_basis(tile_size: int, dtype: np.dtype) -> np.ndarray:  # [5, p]
    """u, v, u^2, uv, v^2 of a tile's pixel centres, as offsets from the tile centre; pixel
    p = row * size + col (the torch backend's ``_pixel_basis`` order)."""
    o = np.arange(tile_size, dtype=np.float64) + 0.5 - 0.5 * tile_size
    v, u = np.meshgrid(o, o, indexing="ij")
    u, v = u.reshape(-1), v.reshape(-1)
    return np.ascontiguousarray(np.stack([u, v, u * u, u * v, v * v]).astype(dtype))


def _threads() -> int:
    assert numba is not None  # only called beside the kernels, which exist only when numba imports
    # NUMBA_NUM_THREADS is set in numba's config module from the environment at import time.
    n_numba = numba_config.NUMBA_NUM_THREADS  # pyright: ignore[reportAttributeAccessIssue]
    n = max(1, min(torch.get_num_threads(), n_numba))
    numba.set_num_threads(n)
    return n


class _NumbaComposite(torch.autograd.Function):
    """Same contract as the torch backend's ``_Composite``: ``kp`` [6, M], ``aug`` [N, D] ->
    per-tile sums [tiles, D, p]."""

    @staticmethod
    def forward(ctx, kp: Tensor, aug: Tensor, bins: Bins, cfg: CompositeConfig):
        dtype = aug.dtype
        np_dtype = np.dtype(np.float32 if dtype == torch.float32 else np.float64)
        n_tiles = bins.tiles_x * bins.tiles_y
        P = bins.tile_size**2
        D = aug.shape[1]
        kp_np = kp.detach().T.contiguous().numpy()  # [M, 6]
        aug_np = aug.detach().contiguous().numpy()
        lens = bins.tile_len
        nonempty = torch.nonzero(lens > 0).squeeze(1)
        order = nonempty[torch.argsort(lens[nonempty], descending=True, stable=True)].numpy()
        basis = _pixel_basis(bins.tile_size, np_dtype)
        out = np.zeros((n_tiles, P, D), dtype=np_dtype)
        stop = np.zeros((n_tiles, P), dtype=np.int64)
        gid = bins.pair_gid.numpy()
        ts, tl = bins.tile_start.numpy(), lens.numpy()
        log_min, log_clamp = math.log2(cfg.alpha_min), math.log2(cfg.alpha_clamp)
        with _LOCK:
            nthreads = _threads()
            _forward_kernel(
                kp_np,
                gid,
                ts,
                tl,
                order,
                aug_np,
                basis,
                np_dtype.type(log_min),
                np_dtype.type(log_clamp),
                np_dtype.type(cfg.transmittance_min),
                nthreads,
                out,
                stop,
            )
        bins.evaluated = int(stop.sum())  # pairs walked (each pixel up to its stop)
        out_t = torch.from_numpy(out).transpose(1, 2)  # [T, D, p], the torch backend's layout
        ctx.bins, ctx.cfg = bins, cfg
        ctx.np = (kp_np, aug_np, order, basis, stop, out, log_min, log_clamp, np_dtype)  # what the backward walks
        return out_t

    @staticmethod
    def backward(ctx, g_out: Tensor):
        kp_np, aug_np, order, basis, stop, out, log_min, log_clamp, np_dtype = ctx.np
        bins = ctx.bins
        g_out_np = g_out.detach().to(torch.float32 if np_dtype == np.float32 else torch.float64).contiguous().numpy()
        g_kp = np.zeros_like(kp_np)
        with _LOCK:
            nthreads = _threads()
            g_aug = np.zeros((nthreads,) + aug_np.shape, dtype=np_dtype)
            _backward_kernel(
                kp_np,
                bins.pair_gid.numpy(),
                bins.tile_start.numpy(),
                order,
                aug_np,
                basis,
                np_dtype.type(log_min),
                np_dtype.type(log_clamp),
                np_dtype.type(_LN2),
                nthreads,
                out,
                g_out_np,
                stop,
                g_kp,
                g_aug,
            )
        for k in range(1, nthreads):
            g_aug[0] += g_aug[k]
        return torch.from_numpy(g_kp).T, torch.from_numpy(g_aug[0]), None, None


def rasterize_numba(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] wxyz
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    features: Tensor,  # [N, C]
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    **kw,  # near, far, eps2d, alpha_clamp, alpha_min, transmittance_min, tile_size, rows
) -> dict:
    """:func:`~n2f2.render.torch_backend.rasterize_torch` with the compiled compositing; the
    same dict (``n_pairs`` counts the pairs the pixels walked, without padding)."""
    if means.device.type != "cpu":
        raise ValueError("the numba backend runs on CPU tensors only")
    return rasterize_torch(
        means, quats, scales, opacities, features, viewmat, K, width, height, composite=_NumbaComposite.apply, **kw
    )
