"""Tile compositing compiled with numba: the CPU fast path of the rasterizer.

The per-Gaussian steps before it are compiled in their own modules, each equal to its torch
reference (:mod:`n2f2.render.numba_project`: the projection and its gradients;
:mod:`n2f2.render.numba_bins`: the tile binning, bit for bit); the per-pair ``log2 alpha``
polynomial is the torch backend's (plain autograd). The compositing, the loop over
pixel-Gaussian pairs, runs here, as two compiled kernels that follow 3DGS's CUDA ones:

* forward: per pixel, walk the tile's depth-sorted list front to back, blend, stop at the
  transmittance limit, and record how many pairs the pixel walked (``stop``) and, when a
  gradient is wanted, which pixels each pair was blended into (``blend``, one bit per pixel);
* backward: per pixel, walk the same pairs front to back again with the same arithmetic,
  carrying the prefix sum ``sum_{j<=i} w_j f_j . g`` so that no division by ``1 - alpha``
  reconstructs a transmittance (the torch backend's formula, written per pair).

The forward walks a tile's list one Gaussian at a time: a branch-free pass over the tile's
pixels evaluates ``log2 alpha`` and collects the pixels above ``alpha_min`` (about a quarter
of the pairs walked in a 3DGS-like scene), and only those are blended. The backward reads
those pixels from the forward's bit masks (8 bytes per pair for 8x8 tiles) instead of testing
every pixel again. The loops over the D channels are the cost for large C; the backward does
them four pixels at a time, and its per-pixel scalar terms in one branch-free pass over the
tile. Dense per-tile products through BLAS (``[p, len] @ [len, D]``) do four times the
multiply-adds at that sparsity and measured slower at C = 64 (a [64, 128] @ [128, 66] float32
product alone took 2.4-3.6 ns per pixel-pair on one core, about the whole sparse blend's cost).

Feature rows are gathered from random places of the ``[N, D]`` table, and the backward's
feature gradients go back there: both kernels ask the CPU to prefetch the rows one step of
Gaussians ahead, which hides most of those cache misses.

Forward tiles are dealt to threads round-robin in order of list length, longest first. The
backward cuts the row-major tile order into one run per thread of about equal work (known from
``stop``): neighbouring tiles share most of their Gaussians, so a Gaussian's feature-gradient
row is written by one thread directly, and only the pairs of Gaussians on the border between
two runs go through a small spill buffer, added afterwards. (One ``[N, D]`` buffer per thread,
zeroed and summed, cost N * D * threads of memory traffic per call.) Per-pair gradients are
written by the one thread that owns the tile (no race).

numba ships its compiler in its wheel, so nothing is built at install time. Kernels are
compiled on first use (about 20 s on 2 cores) and cached on disk beside this file, or in numba's
user cache when that folder is read-only; ``n2f2 demo`` and ``n2f2 run`` start that compile in a
child process while they make or read the scene
(:func:`n2f2.render.numba_runtime.compile_in_background`). Calls are serialised by
:data:`n2f2.render.numba_runtime.KERNEL_LOCK`.

torch's OpenMP threads must not spin-wait through these kernels (with OpenMP's default spin
count a render took 25x longer on 2 cores): the ``n2f2`` command sets ``GOMP_SPINCOUNT`` (see
:mod:`n2f2.cli`); library users on few cores set it, or ``OMP_WAIT_POLICY=PASSIVE``, before
importing torch.

(Longer than 600 lines: the forward and backward kernels, their helpers and the autograd
function share one tile layout and one bit-mask format, and are read together.)
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from n2f2.render.numba_bins import bin_gaussians_numba
from n2f2.render.numba_pairs import pair_coefficients_numba
from n2f2.render.numba_project import project_gaussians_numba
from n2f2.render.numba_runtime import (
    FASTMATH,
    KERNEL_LOCK,
    compile_in_background,  # noqa: F401 - re-exported: the pipeline imports it from here
    kernel_threads,  # noqa: F401 - re-exported: the fit imports it from here
    numba_threads,
    torch_on_one_thread,  # noqa: F401 - re-exported: the fit imports it from here
    wait_for_background_compile,
)
from n2f2.render.torch_backend import Bins, CompositeConfig, rasterize_torch

try:  # optional at import time: the "auto" backend falls back to torch without it
    import numba
    from llvmlite import ir
    from numba import njit, prange, types
    from numba.core import cgutils
    from numba.extending import intrinsic
except ImportError:  # pragma: no cover - numba is a declared dependency
    numba = None

_LN2 = math.log(2.0)


# Gaussians per step of a tile's list: their feature rows are gathered into a per-thread
# buffer first (prefetched during the previous step), and the backward's per-Gaussian feature
# gradients are summed there before one write per Gaussian and step.
_CHUNK = 64
# Where the backward sends a walked pair's feature gradient, besides a row of the spill buffer:
# added to the Gaussian's row, or written to it (the first pair of the thread that owns the row).
_ADD = -1
_SET = -2

if numba is not None:

    @intrinsic
    def _prefetch(typingctx, arr, i, j):
        """Ask the CPU to start loading ``arr[i, j]`` into cache (a prefetch: no wait, no fault)."""

        def codegen(context, builder, signature, args):
            aryty = signature.args[0]
            ary = context.make_array(aryty)(context, builder, args[0])
            ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [args[1], args[2]])
            i8p = ir.IntType(8).as_pointer()
            i32 = ir.IntType(32)
            # Unsuffixed: LLVM names the intrinsic after its pointer type and upgrades the old name.
            fn = cgutils.get_or_insert_function(
                builder.module, ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]), "llvm.prefetch"
            )
            builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])  # read, all cache levels, data
            return context.get_dummy_value()

        return types.void(arr, i, j), codegen

    @intrinsic
    def _ctz(typingctx, x):
        """Index of the lowest set bit of a nonzero uint64."""

        def codegen(context, builder, signature, args):
            return builder.cttz(args[0], ir.Constant(ir.IntType(1), 1))

        return types.uint64(types.uint64), codegen

    @njit(cache=True, nogil=True)
    def _prefetch_row(arr, i):  # arr [n, D]: start loading row i, one cache line at a time
        D = arr.shape[1]
        step = max(1, 64 // arr.itemsize)
        # (pyright reads an intrinsic's typing signature, which takes the typing context first)
        for j in range(0, D, step):
            _prefetch(arr, i, j)  # pyright: ignore[reportCallIssue]
        _prefetch(arr, i, D - 1)  # pyright: ignore[reportCallIssue]

    @njit(parallel=True, fastmath=FASTMATH, cache=True, nogil=True)
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
        blend,  # [M, ceil(p / 64)] uint64 zero-initialised: bit p of row q set where pair q was blended
        # into pixel p; [0, ceil(p / 64)] to record nothing (no backward to follow)
    ):
        P = basis.shape[1]
        D = aug.shape[1]
        record = blend.shape[0] > 0
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
                nxt = ii + nthreads  # this thread's next tile
                s_next = tile_start[order[nxt]] if nxt < order.shape[0] else 0
                n_next = tile_len[order[nxt]] if nxt < order.shape[0] else 0
                for j in range(n):
                    q = s + j
                    jc = j % _CHUNK
                    if jc == 0:
                        for i in range(min(_CHUNK, n - j)):
                            _copy_row(aug[gid[q + i]], A[i])
                    # The row this step's slot holds in the next gathering: loading it now
                    # overlaps the cache misses with the blending.
                    if q + _CHUNK < s + n:
                        _prefetch_row(aug, gid[q + _CHUNK])
                    elif j - jc + _CHUNK >= n and jc < n_next:
                        _prefetch_row(aug, gid[s_next + jc])
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
                    word = np.uint64(0)  # blend bits of pixels 64 * k ... 64 * k + 63 (pixels come in order)
                    k = 0
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
                        if p >> 6 != k:
                            if record:
                                blend[q, k] = word
                            word = np.uint64(0)
                            k = p >> 6
                        word |= np.uint64(1) << np.uint64(p & 63)
                    if record:
                        blend[q, k] = word
                    if n_live == 0:
                        break

    @njit(parallel=True, fastmath=FASTMATH, cache=True, nogil=True)
    def _backward_kernel(
        kp,  # [M, 6]
        gid,  # [M] int64
        tile_start,  # [T]
        tiles,  # [T'] int64 tiles with walked pairs, row-major
        bounds,  # [nthreads + 1] int64: thread t walks tiles[bounds[t]:bounds[t + 1]]
        walked,  # [T] int64 pairs of each tile's list that some pixel walked
        dest,  # [M] int64 where a walked pair's feature gradient goes (see _backward_schedule)
        aug,  # [N, D]
        basis,  # [5, p]
        log_clamp,
        ln2,  # ln2: log(2) in the arrays' type
        out,  # [T, p, D] forward output
        g_out,  # [T, D, p] upstream gradient (the torch backend's layout)
        blend,  # [M, ceil(p / 64)] uint64 from the forward pass
        g_kp,  # [M, 6] zero-initialised
        g_aug,  # [N, D] rows of Gaussians with walked pairs are written here, the rest left alone
        g_spill,  # [S, D] feature gradients of the pairs that dest sends here
    ):
        """The rasterizer's backward: the gradients of each walked pair's blending parameters
        (``g_kp``) and feature row (``g_aug`` or ``g_spill``), one thread per range of tiles.

        One function because numba compiles it into one parallel loop that can call only other
        compiled functions (the small row helpers it uses), not Python helpers, and the state a
        tile carries from Gaussian to Gaussian stays in this frame: the per-pixel transmittance,
        prefix and log-alpha arrays and the chunk's feature rows are allocated once per thread
        and reused for every tile, and the six parameter gradients and the four dot products are
        accumulated in locals. Split into compiled helpers, every Gaussian's call would take a
        dozen of those arrays as arguments and send its accumulators through memory."""
        # O = sum_i w_i f_i, w_i = alpha_i T_i:  dL/dalpha_i = (T_{i+1} fg_i - total + prefix_i) / (1 - alpha_i)
        # with fg_i = f_i . g, total = O . g and prefix_i = sum_{j<=i} w_j fg_j.
        P = basis.shape[1]
        D = aug.shape[1]
        one = ln2 / ln2  # typed 1 and 0, as in the forward
        zero = one - one
        for t in prange(bounds.shape[0] - 1):
            T = np.empty(P, dtype=out.dtype)
            base = np.empty(P, dtype=out.dtype)  # prefix - total
            la = np.empty(P, dtype=out.dtype)  # log2 alpha of the current Gaussian at each pixel
            hit = np.empty(P, dtype=np.int64)  # pixels the current Gaussian was blended into
            wv = np.zeros(P, dtype=out.dtype)  # per pixel: w, alpha and f . g of the step, 0 if not blended
            av = np.zeros(P, dtype=out.dtype)
            fv = np.zeros(P, dtype=out.dtype)
            A = np.empty((_CHUNK, D), dtype=out.dtype)  # feature rows of the step
            GA = np.empty((_CHUNK, D), dtype=out.dtype)  # their gradients, written out after the step
            G = np.empty((P, D), dtype=out.dtype)  # the tile's upstream gradient, one row per pixel
            for ii in range(bounds[t], bounds[t + 1]):
                tile = tiles[ii]
                s = tile_start[tile]
                Gt = g_out[tile]
                for d in range(D):
                    for p in range(P):
                        G[p, d] = Gt[d, p]
                O = out[tile]
                n = walked[tile]
                last = ii + 1 == bounds[t + 1]
                s_next = 0 if last else tile_start[tiles[ii + 1]]
                n_next = 0 if last else walked[tiles[ii + 1]]
                for p in range(P):
                    tot = zero
                    Op = O[p]
                    Gp = G[p]
                    for d in range(D):
                        tot += Op[d] * Gp[d]
                    base[p] = -tot
                    T[p] = 1.0
                for j0 in range(0, n, _CHUNK):
                    m = min(_CHUNK, n - j0)
                    for i in range(m):
                        _copy_row(aug[gid[s + j0 + i]], A[i])
                    GA[:m, :] = 0.0
                    for jc in range(m):
                        j = j0 + jc
                        q = s + j
                        # Rows needed later: the next gathering's (see the forward) and the
                        # gradient row this step's sum is written to after the chunk.
                        if j + _CHUNK < n:
                            _prefetch_row(aug, gid[q + _CHUNK])
                        elif j0 + _CHUNK >= n and jc < n_next:
                            _prefetch_row(aug, gid[s_next + jc])
                        if dest[q] < 0:
                            _prefetch_row(g_aug, gid[q])
                        # The pixels the forward blended this Gaussian into, from its bit mask.
                        c = 0
                        for k in range(blend.shape[1]):
                            bits = blend[q, k]
                            while bits != 0:
                                hit[c] = 64 * k + _ctz(bits)  # pyright: ignore[reportCallIssue]
                                c += 1
                                bits &= bits - np.uint64(1)
                        if c == 0:
                            continue
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
                        a = A[jc]
                        gacc = GA[jc]
                        for i in range(c):
                            p = hit[i]
                            alpha = np.exp2(min(la[p], log_clamp))
                            wv[p] = alpha * T[p]
                            av[p] = alpha
                            T[p] = T[p] * (one - alpha)  # now T_{i+1}
                        # f . g and the feature gradient, four pixels per pass over the channels:
                        # one load and store of the gradient row per four products.
                        i = 0
                        while i + 4 <= c:
                            h0, h1, h2, h3 = hit[i], hit[i + 1], hit[i + 2], hit[i + 3]
                            G0, G1, G2, G3 = G[h0], G[h1], G[h2], G[h3]
                            w0, w1, w2, w3 = wv[h0], wv[h1], wv[h2], wv[h3]
                            f0 = f1 = f2 = f3 = zero
                            for d in range(D):
                                ad = a[d]
                                x0, x1, x2, x3 = G0[d], G1[d], G2[d], G3[d]
                                f0 += ad * x0
                                f1 += ad * x1
                                f2 += ad * x2
                                f3 += ad * x3
                                gacc[d] += w0 * x0 + w1 * x1 + w2 * x2 + w3 * x3
                            fv[h0], fv[h1], fv[h2], fv[h3] = f0, f1, f2, f3
                            i += 4
                        while i < c:
                            h = hit[i]
                            Gp = G[h]
                            w = wv[h]
                            f = zero
                            for d in range(D):
                                gd = Gp[d]
                                f += a[d] * gd
                                gacc[d] += w * gd
                            fv[h] = f
                            i += 1
                        # Over all pixels, branch-free: w, alpha and f . g are 0 where the
                        # Gaussian did not blend, and the term is selected away there (so that
                        # a non-finite upstream gradient stays with its own pixel's pairs).
                        g0 = g1 = g2 = g3 = g4 = g5 = zero
                        for p in range(P):
                            fg = fv[p]
                            alpha = av[p]
                            bp = base[p] + wv[p] * fg
                            base[p] = bp
                            d_la = (T[p] * fg + bp) / (one - alpha) * alpha * ln2
                            # A clamped alpha passes no gradient.
                            d_la = d_la if (alpha > zero) & (la[p] <= log_clamp) else zero
                            g0 += d_la
                            g1 += d_la * basis[0, p]
                            g2 += d_la * basis[1, p]
                            g3 += d_la * basis[2, p]
                            g4 += d_la * basis[3, p]
                            g5 += d_la * basis[4, p]
                            fv[p] = zero
                            wv[p] = zero
                            av[p] = zero
                        g_kp[q, 0] = g0
                        g_kp[q, 1] = g1
                        g_kp[q, 2] = g2
                        g_kp[q, 3] = g3
                        g_kp[q, 4] = g4
                        g_kp[q, 5] = g5
                    for i in range(m):
                        q = s + j0 + i
                        r = dest[q]
                        if r == _ADD:
                            _add_row(GA[i], g_aug[gid[q]])
                        elif r == _SET:
                            _copy_row(GA[i], g_aug[gid[q]])
                        else:
                            _copy_row(GA[i], g_spill[r])

    @njit(cache=True, nogil=True)
    def _copy_row(src, dst):  # [D] -> [D]; a plain loop (a slice assignment checks for overlap first)
        for d in range(src.shape[0]):
            dst[d] = src[d]

    @njit(cache=True, nogil=True)
    def _add_row(src, dst):  # [D] += [D]
        for d in range(src.shape[0]):
            dst[d] += src[d]

    @njit(cache=True, nogil=True)
    def _backward_schedule(
        gid,  # [M] int64
        tile_start,  # [T] int64
        stop,  # [T, p] int64 from the forward pass
        nthreads,
        n_gauss,
    ):
        """Deal the backward's tiles to threads, and say where each pair's feature gradient goes.

        Tiles with walked pairs, in row-major order, are cut into ``nthreads`` runs of about
        equal work, so neighbouring tiles (which share most Gaussians) go to the same thread.
        A Gaussian's gradient row belongs to the first thread whose run reaches it: that thread
        writes it directly (``_SET`` at the Gaussian's first pair, ``_ADD`` after), and other
        threads write their pairs' gradients to rows of a spill buffer, added in afterwards.
        Returns tiles [T'], bounds [nthreads + 1], walked [T] (pairs walked per tile), dest [M]
        (``_SET``, ``_ADD`` or a spill row), the number of spill rows, and touched [N] (False: no
        walked pair, gradient 0)."""
        n_tiles, P = stop.shape
        walked = np.zeros(n_tiles, dtype=np.int64)
        work = np.zeros(n_tiles, dtype=np.int64)
        n = 0
        total = 0
        for tile in range(n_tiles):
            w = 0
            pairs = 0
            for p in range(P):
                w = max(w, stop[tile, p])
                pairs += stop[tile, p]
            walked[tile] = w
            work[tile] = pairs + (P // 2) * w  # pairs walked, plus the per-Gaussian passes over all pixels
            if w > 0:
                n += 1
                total += work[tile]
        tiles = np.empty(n, dtype=np.int64)
        bounds = np.empty(nthreads + 1, dtype=np.int64)
        bounds[0] = 0
        k = 0
        acc = 0
        t = 1
        for tile in range(n_tiles):
            if walked[tile] > 0:
                tiles[k] = tile
                k += 1
                acc += work[tile]
                while t < nthreads and acc * nthreads >= total * t:
                    bounds[t] = k
                    t += 1
        while t <= nthreads:
            bounds[t] = n
            t += 1
        owner = np.full(n_gauss, -1, dtype=np.int64)
        dest = np.full(gid.shape[0], _ADD, dtype=np.int64)
        n_spill = 0
        for t in range(nthreads):
            for k in range(bounds[t], bounds[t + 1]):
                tile = tiles[k]
                for q in range(tile_start[tile], tile_start[tile] + walked[tile]):
                    g = gid[q]
                    if owner[g] < 0:
                        owner[g] = t
                        dest[q] = _SET
                    elif owner[g] != t:
                        dest[q] = n_spill
                        n_spill += 1
        return tiles, bounds, walked, dest, n_spill, owner >= 0

    @njit(cache=True, nogil=True)
    def _finish_feature_grad(
        gid,  # [M] int64
        dest,  # [M] int64
        touched,  # [N] bool
        g_spill,  # [S, D]
        g_aug,  # [N, D]
    ):
        """Add the spilled pair gradients, and zero the rows of Gaussians no pixel walked."""
        for g in range(g_aug.shape[0]):
            if not touched[g]:
                g_aug[g, :] = 0.0
        for q in range(dest.shape[0]):
            r = dest[q]
            if r >= 0:
                _add_row(g_spill[r], g_aug[gid[q]])


def _pixel_basis(tile_size: int, dtype: np.dtype) -> np.ndarray:  # [5, p]
    """u, v, u^2, uv, v^2 of a tile's pixel centres, as offsets from the tile centre; pixel
    p = row * size + col (the torch backend's ``_pixel_basis`` order)."""
    o = np.arange(tile_size, dtype=np.float64) + 0.5 - 0.5 * tile_size
    v, u = np.meshgrid(o, o, indexing="ij")
    u, v = u.reshape(-1), v.reshape(-1)
    return np.ascontiguousarray(np.stack([u, v, u * u, u * v, v * v]).astype(dtype))


def _forward(
    kp: Tensor,  # [6, M]
    aug: Tensor,  # [N, D]
    bins: Bins,
    cfg: CompositeConfig,
    record: bool,  # keep what the backward needs (the blend masks)
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Run the forward kernel: out [T, p, D], stop [T, p], blend [M or 0, ceil(p / 64)], and the
    kernel's own kp [M, 6] and aug [N, D] arrays."""
    np_dtype = np.dtype(np.float32 if aug.dtype == torch.float32 else np.float64)
    n_tiles = bins.tiles_x * bins.tiles_y
    P = bins.tile_size**2
    kp_np = kp.detach().T.contiguous().numpy()  # [M, 6]
    aug_np = aug.detach().contiguous().numpy()
    lens = bins.tile_len
    nonempty = torch.nonzero(lens > 0).squeeze(1)
    order = nonempty[torch.argsort(lens[nonempty], descending=True, stable=True)].numpy()
    out = np.zeros((n_tiles, P, aug_np.shape[1]), dtype=np_dtype)
    stop = np.zeros((n_tiles, P), dtype=np.int64)
    blend = np.zeros((kp_np.shape[0] if record else 0, -(-P // 64)), dtype=np.uint64)
    with KERNEL_LOCK:
        nthreads = numba_threads()
        _forward_kernel(
            kp_np,
            bins.pair_gid.numpy(),
            bins.tile_start.numpy(),
            lens.numpy(),
            order,
            aug_np,
            _pixel_basis(bins.tile_size, np_dtype),
            np_dtype.type(math.log2(cfg.alpha_min)),
            np_dtype.type(math.log2(cfg.alpha_clamp)),
            np_dtype.type(cfg.transmittance_min),
            nthreads,
            out,
            stop,
            blend,
        )
    bins.evaluated = int(stop.sum())  # pairs walked (each pixel up to its stop)
    return out, stop, blend, kp_np, aug_np


class _NumbaComposite(torch.autograd.Function):
    """Same contract as the torch backend's ``_Composite``: ``kp`` [6, M], ``aug`` [N, D] ->
    per-tile sums [tiles, D, p]; ``record`` False (no gradient wanted) skips the blend masks."""

    @staticmethod
    def forward(ctx, kp: Tensor, aug: Tensor, bins: Bins, cfg: CompositeConfig, record: bool):
        out, stop, blend, kp_np, aug_np = _forward(kp, aug, bins, cfg, record)
        ctx.bins, ctx.cfg = bins, cfg
        ctx.np = (kp_np, aug_np, stop, blend, out)  # what the backward walks
        return torch.from_numpy(out).transpose(1, 2)  # [T, D, p], the torch backend's layout

    @staticmethod
    def backward(ctx, g_out: Tensor):
        kp_np, aug_np, stop, blend, out = ctx.np
        bins, cfg = ctx.bins, ctx.cfg
        if blend.shape[0] != kp_np.shape[0]:
            raise RuntimeError("the numba compositing ran without gradients enabled; no backward through it")
        np_dtype = aug_np.dtype
        g_np = g_out.detach().to(torch.float32 if np_dtype == np.float32 else torch.float64).contiguous().numpy()
        gid = bins.pair_gid.numpy()
        tile_start = bins.tile_start.numpy()
        N, D = aug_np.shape
        g_kp = np.zeros_like(kp_np)
        g_aug = np.empty_like(aug_np)  # every row is written: by the kernel, or zeroed after it
        with KERNEL_LOCK:
            nthreads = numba_threads()
            tiles, bounds, walked, dest, n_spill, touched = _backward_schedule(gid, tile_start, stop, nthreads, N)
            g_spill = np.empty((n_spill, D), dtype=np_dtype)
            _backward_kernel(
                kp_np,
                gid,
                tile_start,
                tiles,
                bounds,
                walked,
                dest,
                aug_np,
                _pixel_basis(bins.tile_size, np_dtype),
                np_dtype.type(math.log2(cfg.alpha_clamp)),
                np_dtype.type(_LN2),
                out,
                g_np,
                blend,
                g_kp,
                g_aug,
                g_spill,
            )
            _finish_feature_grad(gid, dest, touched, g_spill, g_aug)
        return torch.from_numpy(g_kp).T, torch.from_numpy(g_aug), None, None, None


def _composite(kp: Tensor, aug: Tensor, bins: Bins, cfg: CompositeConfig) -> Tensor:  # [T, D, p]
    # The blend masks cost 8 bytes per pair for 8x8 tiles; without gradients they are not kept.
    record = torch.is_grad_enabled() and (kp.requires_grad or aug.requires_grad)
    return _NumbaComposite.apply(kp, aug, bins, cfg, record)


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
    **kw,  # near, far, eps2d, alpha_clamp, alpha_min, transmittance_min, tile_size, rows, composite
) -> dict:
    """:func:`~n2f2.render.torch_backend.rasterize_torch` with the compiled compositing; the
    same dict (``n_pairs`` counts the pairs the pixels walked, without padding)."""
    if means.device.type != "cpu":
        raise ValueError("the numba backend runs on CPU tensors only")
    wait_for_background_compile()
    kw.setdefault("composite", _composite)  # count_pairs passes a counting one
    return rasterize_torch(
        means, quats, scales, opacities, features, viewmat, K, width, height, **compiled_steps(), **kw
    )


def compiled_steps() -> dict:
    """The CPU renderer's projection, binning and pair coefficients, compiled (each falls back to
    its torch reference for inputs it does not take), as :func:`rasterize_torch` takes them;
    whatever must blend with the renderer's weights uses these too."""
    return {"binning": bin_gaussians_numba, "project": project_gaussians_numba, "coefficients": pair_coefficients_numba}


@torch.no_grad()
def count_pairs(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] wxyz
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    features: Tensor,  # [N, C]
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    **kw,  # rasterize_numba's options
) -> tuple[int, int]:
    """Pixel-Gaussian pairs of one render with the numba backend: (walked, blended). Walked:
    each pixel's tile list up to where it stops; blended: those with alpha >= alpha_min, the
    ones that carry the per-channel work. For benchmarks (their floors)."""
    counts = []

    def composite(kp: Tensor, aug: Tensor, bins: Bins, cfg: CompositeConfig) -> Tensor:
        out, stop, blend, _, _ = _forward(kp, aug, bins, cfg, record=True)
        counts.extend([int(stop.sum()), int(np.unpackbits(blend.view(np.uint8)).sum())])
        return torch.from_numpy(out).transpose(1, 2)

    rasterize_numba(means, quats, scales, opacities, features, viewmat, K, width, height, composite=composite, **kw)
    return counts[0], counts[1]
