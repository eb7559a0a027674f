"""Pure-PyTorch tiled Gaussian rasterizer (runs on any device, used on CPU).

Pipeline (the same maths as 3DGS / gsplat "classic" mode, OpenCV camera, pixel centres at +0.5):

1. :func:`project_gaussians` (plain autograd): camera-space means, EWA 2D covariance with the
   ``eps2d`` low-pass dilation, its inverse (the "conic"), projected centres ``means2d`` and the
   screen-space bounding box of the region where ``alpha >= alpha_min``. That box is exact, so
   binning by it drops nothing the compositing would keep.
2. :func:`bin_gaussians` (no grad, vectorised): global depth sort, one (tile, Gaussian) pair per
   overlapped tile, pairs ordered by (tile, depth).
3. :func:`pair_coefficients` (plain autograd): for each pair, ``log2 alpha`` at a pixel offset
   ``(u, v)`` from the tile centre is ``[1, u, v, u^2, uv, v^2] . k``; the 6 coefficients ``k``
   depend on the Gaussian's log-opacity, conic and centre offset.
4. :class:`_Composite` (custom autograd.Function): tiles sorted by list length and batched; each
   batch walks its lists in chunks of ``chunk`` Gaussians: alpha block = one small matmul + a
   clamped exp2, transmittance by cumprod carried across chunks, early termination, features
   (plus z and 1, giving the depth sum and alpha) accumulated with bmm (any channel count),
   finished tiles dropped. The backward pass recomputes every chunk front to back instead of
   storing it, so memory stays bounded by the inputs plus one batch.

Cost per evaluated pixel-Gaussian pair: ``docs/measurements.md`` ("CPU rasterizer").

Rules (3DGS): ``alpha = min(o * exp(-d^T conic d / 2), alpha_clamp)``; ``alpha < alpha_min``
contributes nothing; the Gaussian that would bring the transmittance below
``transmittance_min`` is not blended and the pixel stops.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, overload

import torch
from torch import Tensor

LOG2E = 1.0 / math.log(2.0)

# ---------------------------------------------------------------------------------- projection
# Per-Gaussian quantities are kept "structure of arrays" ([3, N] rather than [N, 3]): on CPU,
# stacking along the last dimension and batched 3x3 matmuls cost 10-50x more than row ops.


def quat_to_rotmat(quats: Tensor) -> Tensor:  # quats [N, 4] wxyz -> [3, 3, N]
    """Rotation matrices (entry [i, j, n]) of wxyz quaternions, normalised here."""
    q = quats.T.contiguous()  # [4, N]
    q = q * torch.rsqrt((q * q).sum(0))
    w, x, y, z = q
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=0,
    ).reshape(3, 3, -1)


@dataclass
class Projection:
    """Per-Gaussian screen-space quantities for one camera."""

    means2d: Tensor  # [N, 2] projected centres (u, v), differentiable
    conics: Tensor  # [3, N] rows a, b, c of the inverse 2D covariance [[a, b], [b, c]], differentiable
    depths: Tensor  # [N] camera-space z, differentiable
    half_extent: Tensor  # [2, N] half-widths (x, y) of the alpha >= alpha_min box (no grad)
    valid: Tensor  # [N] bool: in front of the camera, inside near/far, reachable alpha


def project_gaussians(
    means: Tensor,  # [N, 3] world-space centres
    quats: Tensor,  # [N, 4] wxyz rotations (normalised here)
    scales: Tensor,  # [N, 3] standard deviations along the local axes (not log)
    opacities: Tensor,  # [N] in (0, 1)
    viewmat: Tensor,  # [4, 4] world-to-camera (OpenCV axes)
    K: Tensor,  # [3, 3] intrinsics
    width: int,
    height: int,
    *,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    alpha_min: float = 1.0 / 255.0,
) -> Projection:
    """EWA splatting projection, as 3DGS: ``Sigma2d = J W Sigma W^T J^T + eps2d I``.

    As in 3DGS/gsplat, the Jacobian is evaluated at the centre's x/z and y/z clamped to 1.3x
    the field of view, so Gaussians far outside the image do not get huge footprints."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    pc = R @ means.T + t[:, None]  # [3, N] camera space
    x, y, z = pc
    valid = (z > near) & (z < far)
    z = torch.where(valid, z, torch.ones_like(z))  # keeps culled entries finite (no NaN grads)
    iz = 1.0 / z

    # Rows of T = J W R_q diag(s) (2 x 3 per Gaussian); Sigma2d = T T^T + eps2d I.
    rot = quat_to_rotmat(quats)  # [3, 3, N]
    M = (R @ rot.reshape(3, -1)).reshape(3, 3, -1) * scales.T[None]  # [3, 3, N] = W R_q diag(s)
    lim_x_pos = (width - cx) / fx + 0.15 * width / fx
    lim_x_neg = cx / fx + 0.15 * width / fx
    lim_y_pos = (height - cy) / fy + 0.15 * height / fy
    lim_y_neg = cy / fy + 0.15 * height / fy
    txz = (x * iz).clamp(-lim_x_neg, lim_x_pos)  # clamped x / z
    tyz = (y * iz).clamp(-lim_y_neg, lim_y_pos)
    t0 = (M[0] - M[2] * txz) * (fx * iz)  # [3, N]
    t1 = (M[1] - M[2] * tyz) * (fy * iz)
    ca = (t0 * t0).sum(0) + eps2d
    cb = (t0 * t1).sum(0)
    cc = (t1 * t1).sum(0) + eps2d
    det = ca * cc - cb * cb
    valid = valid & (det > 0)
    inv_det = 1.0 / torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([cc * inv_det, -cb * inv_det, ca * inv_det], dim=0)
    means2d = torch.stack([fx * x * iz + cx, fy * y * iz + cy], dim=1)

    with torch.no_grad():
        # alpha >= alpha_min  <=>  d^T conic d <= 2 log(o / alpha_min); the ellipse's bounding
        # box has half-widths sqrt(2 log(o / alpha_min) * Sigma_xx) (and _yy).
        level = 2.0 * torch.log(opacities.detach().clamp_min(1e-30) / alpha_min)
        valid = valid & (level > 0) & torch.isfinite(means2d).all(1)
        level = level.clamp_min(0.0)
        half_extent = torch.stack([torch.sqrt(level * ca), torch.sqrt(level * cc)], dim=0)
    return Projection(means2d, conics, pc[2], half_extent, valid)


# ------------------------------------------------------------------------------------- binning
@dataclass
class Bins:
    """(tile, Gaussian) pairs ordered by (tile, depth), and the tile schedule."""

    pair_gid: Tensor  # [M] long, Gaussian index of each pair
    pair_tile: Tensor  # [M] long, tile index (row-major over tiles_y x tiles_x)
    tile_start: Tensor  # [T] long, first pair of each tile
    tile_len: Tensor  # [T] long, number of pairs of each tile
    tiles_x: int
    tiles_y: int
    tile_size: int
    radii: Tensor  # [N] int32, ceil of the larger half-extent, 0 if the Gaussian touches no tile
    evaluated: int = 0  # pixel-Gaussian pairs the last forward composited (padding included)
    row0: int = 0  # image row of the tiles' first row (a band of a larger image; a multiple of tile_size)


@torch.no_grad()
def bin_gaussians(
    means2d: Tensor,  # [N, 2]
    half_extent: Tensor,  # [2, N]
    depths: Tensor,  # [N]
    valid: Tensor,  # [N] bool
    width: int,
    height: int,
    tile_size: int = 8,
    row0: int = 0,  # bin only image rows [row0, row0 + height): one band of a taller image
) -> Bins:
    """Assign depth-sorted Gaussians to the tiles whose pixel centres their box covers."""
    device = means2d.device
    if row0 % tile_size:
        raise ValueError(f"a band must start on a tile row: row0 = {row0}, tile size {tile_size}")
    tiles_x = -(-width // tile_size)
    tiles_y = -(-height // tile_size)
    ok = valid.clone()
    lo, hi = [], []
    for axis, start, size in ((0, 0, width), (1, row0, height)):
        m = means2d[:, axis].detach()
        h = half_extent[axis] + 1e-3  # margin: float rounding never drops a pixel the reference keeps
        # Pixel index i has its centre at i + 0.5; covered: ceil(m - h - .5) .. floor(m + h - .5).
        a = torch.ceil(m - h - 0.5).clamp_(min=float(start)) - start
        b = torch.floor(m + h - 0.5).clamp_(max=start + size - 1.0) - start
        ok &= a <= b
        lo.append(a)
        hi.append(b)
    zero = torch.zeros((), dtype=means2d.dtype, device=device)
    x0, y0, x1, y1 = (
        torch.where(ok, v, zero).long().div_(tile_size, rounding_mode="floor") for v in (lo[0], lo[1], hi[0], hi[1])
    )
    sx = x1 - x0 + 1
    counts = torch.where(ok, sx * (y1 - y0 + 1), 0)  # [N] tiles per Gaussian

    # Depth order; Gaussians generated in that order keep it after a stable sort by tile.
    # Positive floats order like their bit patterns, and integer sorts are radix sorts
    # (3-10x faster on CPU than float sorts).
    key = torch.where(ok, depths.detach(), math.inf)
    key = key.view(torch.int32 if key.dtype == torch.float32 else torch.int64)
    order = torch.argsort(key, stable=True)[: int(ok.sum())]
    c = counts[order]
    total = int(c.sum())
    gid = torch.repeat_interleave(order, c)  # [M]
    first = torch.cumsum(c, 0) - c
    local = (torch.arange(total, device=device) - torch.repeat_interleave(first, c)).int()
    w = sx[gid].int()
    row = local.div(w, rounding_mode="floor")
    tile = (y0[gid].int() + row) * tiles_x + x0[gid].int() + (local - row * w)
    tile, perm = torch.sort(tile, stable=True)
    gid = gid[perm]
    tile = tile.long()
    n_tiles = tiles_x * tiles_y
    tile_len = torch.bincount(tile, minlength=n_tiles)
    tile_start = torch.cumsum(tile_len, 0) - tile_len
    radii = torch.where(ok, torch.ceil(half_extent.amax(0)), 0.0).to(torch.int32)
    return Bins(gid, tile, tile_start, tile_len, tiles_x, tiles_y, tile_size, radii, row0=row0)


def pair_coefficients(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [3, N]
    opacities: Tensor,  # [N]
    bins: Bins,
) -> Tensor:  # [6, M]
    """``log2 alpha`` of pair (tile, g) at offset (u, v) from the tile centre = [1,u,v,u²,uv,v²]·k.

    Working relative to the tile centre keeps the polynomial well conditioned in float32;
    base 2 because exp2 is about twice as fast as exp on CPU."""
    ts = bins.tile_size
    # The clamp keeps log finite (and its gradient free of 0/0) for opacities that underflowed
    # to 0; such Gaussians are never binned.
    table = torch.cat([torch.log(opacities.clamp_min(1e-30))[None], means2d.T, conics], dim=0)  # [6, N]
    logo, mx, my, a, b, c = table.index_select(1, bins.pair_gid)  # [M] each
    dx = (bins.pair_tile % bins.tiles_x).to(mx.dtype).mul_(ts).add_(0.5 * ts) - mx
    dy = (bins.pair_tile // bins.tiles_x).to(my.dtype).mul_(ts).add_(0.5 * ts + bins.row0) - my
    adx = a * dx
    cdy = c * dy
    bdy = b * dy
    return LOG2E * torch.stack(
        [logo - 0.5 * adx * dx - bdy * dx - 0.5 * cdy * dy, -adx - bdy, -b * dx - cdy, -0.5 * a, -b, -0.5 * c],
        dim=0,
    )


def _pixel_basis(tile_size: int, dtype: torch.dtype, device: torch.device) -> Tensor:  # [P, 6]
    o = torch.arange(tile_size, dtype=dtype, device=device) + 0.5 - 0.5 * tile_size
    v, u = torch.meshgrid(o, o, indexing="ij")  # pixel p = row * tile_size + col
    u, v = u.reshape(-1), v.reshape(-1)
    return torch.stack([torch.ones_like(u), u, v, u * u, u * v, v * v], dim=-1)


# ---------------------------------------------------------------------------------- compositing
@dataclass
class CompositeConfig:
    alpha_clamp: float = 0.99  # upper limit of one Gaussian's alpha (3DGS 0.99, gsplat 0.999)
    alpha_min: float = 1.0 / 255.0  # alphas below this contribute nothing
    transmittance_min: float = 1e-4  # stop a pixel before its transmittance drops below this
    chunk: int = 128  # Gaussians per step of a tile list
    batch_elements: int = 1 << 17  # tiles per batch ~ batch_elements / (pixels per tile * chunk)


class _Schedule:
    """Non-empty tiles sorted by list length (longest first) and cut into batches, so tiles
    of a batch have similar lengths and little padding."""

    def __init__(self, bins: Bins, cfg: CompositeConfig):
        lens = bins.tile_len
        tiles = torch.nonzero(lens > 0).squeeze(1)
        order = torch.argsort(lens[tiles], descending=True, stable=True)
        self.tiles = tiles[order]
        per = max(1, cfg.batch_elements // (bins.tile_size**2 * cfg.chunk))
        self.batches = [b for b in torch.split(self.tiles, per) if b.numel() > 0]


def _gather_batch(kp: Tensor, bins: Bins, tiles: Tensor):
    """Pad the pair lists of a batch of tiles to a common length.

    Returns pos [B, L] (pair index, clamped), pad [B, L] bool (True = padding), lens [B]."""
    lens = bins.tile_len[tiles]
    L = int(lens.max())
    ar = torch.arange(L, device=kp.device)
    pad = ar[None, :] >= lens[:, None]
    pos = (bins.tile_start[tiles][:, None] + ar[None, :]).clamp(max=max(kp.shape[1] - 1, 0))
    return pos, pad, lens


def _padded_coefficients(kp: Tensor, pos: Tensor, pad: Tensor) -> Tensor:  # [B, 6, L]
    """Coefficients of a batch; padding entries get log2 alpha = -1e4 everywhere (alpha 0)."""
    kb = kp.detach()[:, pos].masked_fill_(pad[None], 0.0)
    kb[0].masked_fill_(pad, -1e4)
    return kb.permute(1, 0, 2).contiguous()


def _thresholds(cfg: CompositeConfig, dtype: torch.dtype) -> tuple[float, float, float, float]:
    """log2 alpha_min, log2 alpha_clamp, and the largest values below alpha_min and
    transmittance_min, so that ``F.threshold(x, t, 0)`` keeps exactly ``x >= limit``."""

    def below(v: float) -> float:
        return float(torch.nextafter(torch.tensor(v, dtype=dtype), torch.tensor(0.0, dtype=dtype)))

    return math.log2(cfg.alpha_min), math.log2(cfg.alpha_clamp), below(cfg.alpha_min), below(cfg.transmittance_min)


@overload
def _chunk(
    kc: Tensor, P: Tensor, T: Tensor, th: tuple[float, float, float, float], for_backward: Literal[False] = False
) -> tuple[Tensor, Tensor, None]: ...


@overload
def _chunk(
    kc: Tensor, P: Tensor, T: Tensor, th: tuple[float, float, float, float], for_backward: Literal[True]
) -> tuple[Tensor, Tensor, Tensor]: ...


def _chunk(
    kc: Tensor, P: Tensor, T: Tensor, th: tuple[float, float, float, float], for_backward: bool = False
) -> tuple[Tensor, Tensor, Tensor | None]:
    """Blending of one chunk of ``k`` Gaussians over a batch of ``b`` tiles of ``p`` pixels.

    kc [b, 6, k] pair coefficients (padding gives log2 alpha = -1e4), P [p, 6] pixel basis,
    T [b, p] transmittance entering the chunk (0 marks a pixel that has stopped), th from
    :func:`_thresholds`.

    Returns w [b, p, k] blending weights, T_next [b, p, k] transmittance after each Gaussian
    (0 from the first Gaussian that is not blended on), and for the backward pass also
    ``odds`` = alpha / (1 - alpha), zeroed where alpha does not depend smoothly on k
    (cut, clamped, or not blended).

    Weights use w_i = alpha_i T_i = T_next_i * alpha_i / (1 - alpha_i), which needs no
    exclusive cumprod; ``1 - alpha >= 1 - alpha_clamp > 0`` keeps the division safe.
    Masks are built with sign() on floats: boolean compare/masked_fill cost 5-10x more on CPU."""
    log_min, log_clamp, alpha_cut, t_cut = th
    la = torch.matmul(P, kc)  # [b, p, k] log2 alpha
    # Clamp below before exp2: the slow denormal path is avoided and the clamp at
    # log_min - 1 lands under the cut, which then zeroes it.
    la.clamp_(min=log_min - 1.0, max=log_clamp)
    # 1 where alpha is below the clamp (depends on k), 0 where clamped.
    smooth = (log_clamp - la).sign_() if for_backward else None
    alpha = la.exp2_()
    torch.threshold_(alpha, alpha_cut, 0.0)
    one_m = 1.0 - alpha
    odds = alpha.div_(one_m)  # alpha is not needed any more
    one_m[:, :, 0] *= T  # so that the cumprod starts from the incoming transmittance
    T_next = one_m.cumprod_(2)
    # A pixel stops before the Gaussian that would take T below transmittance_min; T_next is
    # non-increasing, so zeroing it there zeroes every later weight too.
    torch.threshold_(T_next, t_cut, 0.0)
    if not for_backward:
        return odds.mul_(T_next), T_next, None
    w = odds * T_next
    assert smooth is not None  # computed above whenever for_backward is set
    odds.mul_(smooth.mul_(torch.sign(T_next)))  # not blended: T_next == 0
    return w, T_next, odds


def _take(idx: Tensor, *xs: Tensor) -> list[Tensor]:
    """Rows ``idx`` of each tensor (index_select is much cheaper than boolean indexing)."""
    return [x.index_select(0, idx) for x in xs]


class _Composite(torch.autograd.Function):
    """Tile compositing. Input ``aug`` [N, D] holds each Gaussian's features with two extra
    columns, z and 1, so that one bmm yields features, the depth sum and alpha = sum w.

    Accumulators are kept transposed ([tiles, D, p]): MKL is 5x faster on the products in
    that orientation when D is small. Tiles that finish (every pixel stopped, or list
    exhausted) are dropped from the batch state so later chunks only process live tiles."""

    @staticmethod
    def forward(ctx, kp: Tensor, aug: Tensor, bins: Bins, cfg: CompositeConfig):
        # kp [6, M], aug [N, D] -> per-tile sums [tiles, D, p]
        device, dtype = aug.device, aug.dtype
        n_tiles = bins.tiles_x * bins.tiles_y
        p = bins.tile_size**2
        D = aug.shape[1]
        P = _pixel_basis(bins.tile_size, dtype, device)
        out = torch.zeros(n_tiles, D, p, dtype=dtype, device=device)
        th = _thresholds(cfg, dtype)
        evaluated = 0
        for tiles in _Schedule(bins, cfg).batches:
            pos, pad, lens = _gather_batch(kp, bins, tiles)
            kb = _padded_coefficients(kp, pos, pad)  # [B, 6, L]
            gb = bins.pair_gid[pos]  # [B, L]
            T = torch.ones(tiles.shape[0], p, dtype=dtype, device=device)
            acc = torch.zeros(tiles.shape[0], D, p, dtype=dtype, device=device)
            for c0 in range(0, kb.shape[2], cfg.chunk):
                gc = gb[:, c0 : c0 + cfg.chunk]
                w, T_next, _ = _chunk(kb[:, :, c0 : c0 + cfg.chunk], P, T, th)
                f = aug.index_select(0, gc.reshape(-1)).view(*gc.shape, D)  # [b, k, D]
                acc.baddbmm_(f.transpose(1, 2), w.transpose(1, 2))
                evaluated += w.numel()
                T = T_next[:, :, -1]
                finished = (T.amax(1) == 0) | (lens <= c0 + cfg.chunk)
                if bool(finished.any()):
                    done = finished.nonzero().squeeze(1)
                    out.index_copy_(0, tiles.index_select(0, done), acc.index_select(0, done))
                    keep = (~finished).nonzero().squeeze(1)
                    if keep.numel() == 0:
                        break
                    kb, gb, T, acc, lens, tiles = _take(keep, kb, gb, T, acc, lens, tiles)
        bins.evaluated = evaluated
        ctx.bins, ctx.cfg = bins, cfg
        ctx.save_for_backward(kp, aug, out)
        return out

    @staticmethod
    def backward(ctx, g_out: Tensor):
        # O_c = sum_i w_i f_ic with w_i = alpha_i prod_{j<i} (1 - alpha_j), so with fg_i = f_i . g:
        # dL/dalpha_i = T_i fg_i - (sum_{j>i} w_j fg_j) / (1 - alpha_i)
        #             = (T_next_i fg_i - total + sum_{j<=i} w_j fg_j) / (1 - alpha_i),
        # total = sum_j w_j fg_j = O . g. Walking front to back, the prefix sum is carried.
        # d alpha / d log2 alpha = alpha ln 2.
        kp, aug, out = ctx.saved_tensors
        bins, cfg = ctx.bins, ctx.cfg
        device, dtype = aug.device, aug.dtype
        D = aug.shape[1]
        p = bins.tile_size**2
        P = _pixel_basis(bins.tile_size, dtype, device)
        PT = P.T.contiguous()
        g_kp = torch.zeros_like(kp)
        # index_add_ along dim 1 of a transposed buffer is 2x faster for few channels, 3-30x
        # slower for many.
        few = D <= 16
        g_aug = torch.zeros(D, aug.shape[0], dtype=dtype, device=device) if few else torch.zeros_like(aug)
        g_out = g_out.contiguous()
        total_all = (out * g_out).sum(1)  # [tiles, p]
        th = _thresholds(cfg, dtype)
        for tiles in _Schedule(bins, cfg).batches:
            pos, pad, lens = _gather_batch(kp, bins, tiles)
            kb = _padded_coefficients(kp, pos, pad)  # [B, 6, L]
            gb = bins.pair_gid[pos]
            B = tiles.shape[0]
            gkb = torch.zeros_like(kb)
            rows = torch.arange(B, device=device)  # batch row of each live tile
            T = torch.ones(B, p, dtype=dtype, device=device)
            g = g_out.index_select(0, tiles)  # [B, D, p]
            base = -total_all.index_select(0, tiles)  # prefix - total, [B, p]
            for c0 in range(0, kb.shape[2], cfg.chunk):
                gc = gb[:, c0 : c0 + cfg.chunk]
                w, T_next, odds = _chunk(kb[:, :, c0 : c0 + cfg.chunk], P, T, th, for_backward=True)
                idx = gc.reshape(-1)
                f = aug.index_select(0, idx).view(*gc.shape, D)  # [b, k, D]
                fg = torch.bmm(g.transpose(1, 2), f.transpose(1, 2))  # [b, p, k]
                cs = w * fg
                cs[:, :, 0] += base  # the cumsum then carries prefix - total
                cs = cs.cumsum_(2)
                d_la = torch.addcmul(cs, fg, T_next).mul_(odds)  # dL / d log2 alpha, divided by ln 2
                gk = torch.matmul(PT, d_la).mul_(math.log(2.0))  # [b, 6, k]
                if rows.shape[0] == B:
                    gkb[:, :, c0 : c0 + cfg.chunk] = gk
                else:
                    gkb[rows, :, c0 : c0 + cfg.chunk] = gk
                if few:  # [b, D, k] is the fast product orientation for small D
                    g_aug.index_add_(1, idx, torch.bmm(g, w).transpose(0, 1).reshape(D, -1))
                else:  # [b, k, D] directly, no transposed copy
                    g_aug.index_add_(0, idx, torch.bmm(w.transpose(1, 2), g.transpose(1, 2)).view(-1, D))
                base = cs[:, :, -1]
                T = T_next[:, :, -1]
                finished = (T.amax(1) == 0) | (lens <= c0 + cfg.chunk)
                if bool(finished.any()):
                    keep = (~finished).nonzero().squeeze(1)
                    if keep.numel() == 0:
                        break
                    kb, gb, T, g, base, lens, rows = _take(keep, kb, gb, T, g, base, lens, rows)
            sel = (~pad).reshape(-1).nonzero().squeeze(1)
            g_kp.index_copy_(
                1, pos.reshape(-1).index_select(0, sel), gkb.transpose(0, 1).reshape(6, -1).index_select(1, sel)
            )
        return g_kp, (g_aug.T if few else g_aug), None, None


def _untile(x: Tensor, bins: Bins, width: int, height: int) -> Tensor:
    """[tiles, C, p] -> [H, W, C]."""
    ts = bins.tile_size
    C = x.shape[1]
    img = x.reshape(bins.tiles_y, bins.tiles_x, C, ts, ts).permute(0, 3, 1, 4, 2)
    return img.reshape(bins.tiles_y * ts, bins.tiles_x * ts, C)[:height, :width]


def rasterize_torch(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] wxyz
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    features: Tensor,  # [N, C]
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    *,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    alpha_clamp: float = 0.99,
    alpha_min: float = 1.0 / 255.0,
    transmittance_min: float = 1e-4,
    tile_size: int = 8,
    chunk: int = 128,
    batch_elements: int = 1 << 17,
    composite=None,  # the compositing autograd Function's apply; default: this module's
    binning=None,  # bin_gaussians or an equal compiled one; default: this module's
    project=None,  # project_gaussians or an equal compiled one; default: this module's
    coefficients=None,  # pair_coefficients or an equal compiled one; default: this module's
    rows: tuple[int, int] | None = None,  # render only image rows [y0, y1) (y0 on a tile row)
) -> dict:
    """Rasterize with the pure-PyTorch backend.

    ``chunk``: Gaussians per step of a tile list; ``batch_elements``: tiles per batch are
    chosen so one [tiles, pixels, chunk] block has about this many elements (cache-sized).
    ``composite(kp, aug, bins, cfg) -> [tiles, D, p]`` replaces the compositing step (the
    numba backend passes its compiled one).

    Returns a dict: features [H, W, C], alpha [H, W, 1], depth_sum [H, W, 1] (sum w_i z_i,
    not normalised), means2d [N, 2], radii [N] int32, n_pairs (int, pixel-Gaussian pairs the
    forward compositing evaluated, padding included, early-stopped tiles not; for benchmarks).

    ``rows``: the features, alpha and depth of those rows only ([y1 - y0, W, ...]), exactly as
    in the whole image: the projection is the whole image's (3DGS's Jacobian clamp depends on
    the image bounds), and the tiles and their centres are the whole image's tiles."""
    proj = (project or project_gaussians)(
        means, quats, scales, opacities, viewmat, K, width, height, near=near, far=far, eps2d=eps2d, alpha_min=alpha_min
    )
    y0, y1 = rows if rows is not None else (0, height)
    if not 0 <= y0 < y1 <= height:
        raise ValueError(f"rows [{y0}, {y1}) are not inside an image of height {height}")
    height = y1 - y0
    bins = (binning or bin_gaussians)(
        proj.means2d, proj.half_extent, proj.depths, proj.valid, width, height, tile_size, row0=y0
    )
    kp = (coefficients or pair_coefficients)(proj.means2d, proj.conics, opacities, bins)
    cfg = CompositeConfig(
        alpha_clamp=alpha_clamp,
        alpha_min=alpha_min,
        transmittance_min=transmittance_min,
        chunk=chunk,
        batch_elements=batch_elements,
    )
    ones = torch.ones_like(proj.depths)[:, None]
    aug = torch.cat([features, proj.depths[:, None], ones], dim=1)  # [N, C + 2]
    out = _untile((composite or _Composite.apply)(kp, aug, bins, cfg), bins, width, height)  # [H, W, C + 2]
    C = features.shape[1]
    return {
        "features": out[..., :C],
        "alpha": out[..., C + 1 :],
        "depth_sum": out[..., C : C + 1],
        "means2d": proj.means2d,
        "radii": bins.radii,
        "n_pairs": bins.evaluated,
    }
