"""Pure-PyTorch tiled Gaussian rasterizer (runs on any device, used on CPU).

Pipeline (the same maths as 3DGS / gsplat "classic" mode, OpenCV camera, pixel centres at +0.5):

1. :func:`project_gaussians` (plain autograd): camera-space means, EWA 2D covariance with the
   ``eps2d`` low-pass dilation, its inverse (the "conic"), projected centres ``means2d`` and the
   screen-space bounding box of the region where ``alpha >= alpha_min``. That box is exact, so
   binning by it drops nothing the compositing would keep.
2. :func:`bin_gaussians` (no grad, vectorised): global depth sort, one (tile, Gaussian) pair per
   overlapped tile, pairs ordered by (tile, depth).
3. :func:`pair_coefficients` (plain autograd): for each pair, ``log alpha`` at a pixel offset
   ``(u, v)`` from the tile centre is ``[1, u, v, u^2, uv, v^2] . k``; the 6 coefficients ``k``
   depend on the Gaussian's log-opacity, conic and centre offset.
4. :class:`_Composite` (custom autograd.Function): tiles sorted by list length and batched; each
   batch walks its lists in chunks of ``chunk`` Gaussians: alpha block = one small matmul + a
   clamped exp, transmittance by cumprod carried across chunks, early termination, features
   accumulated with bmm (any channel count), finished tiles dropped. The backward pass
   recomputes every chunk front to back instead of storing it, so memory stays bounded by the
   inputs plus one batch.

Rules (3DGS): ``alpha = min(o * exp(-d^T conic d / 2), alpha_clamp)``; ``alpha < alpha_min``
contributes nothing; the Gaussian that would bring the transmittance below
``transmittance_min`` is not blended and the pixel stops.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor


# ---------------------------------------------------------------------------------- projection
def quat_to_rotmat(quats: Tensor) -> Tensor:  # quats [N, 4] wxyz -> [N, 3, 3]
    """Rotation matrices of (not necessarily unit) wxyz quaternions; normalised here."""
    w, x, y, z = F.normalize(quats, dim=-1).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(quats.shape[:-1] + (3, 3))


@dataclass
class Projection:
    """Per-Gaussian screen-space quantities for one camera."""

    means2d: Tensor  # [N, 2] projected centres (u, v), differentiable
    conics: Tensor  # [N, 3] (a, b, c) of the inverse 2D covariance [[a, b], [b, c]], differentiable
    depths: Tensor  # [N] camera-space z, differentiable
    half_extent: Tensor  # [N, 2] half-widths (x, y) of the alpha >= alpha_min box (no grad)
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
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    p = means @ R.T + t  # [N, 3] camera space
    x, y, z = p.unbind(-1)
    valid = (z > near) & (z < far)
    z_safe = torch.where(valid, z, torch.ones_like(z))  # keeps culled rows finite (no NaN grads)

    rot = quat_to_rotmat(quats)  # [N, 3, 3]
    M = R @ rot * scales[:, None, :]  # [N, 3, 3] camera-space R_cam R_q diag(s)
    cov_cam = M @ M.transpose(1, 2)  # [N, 3, 3]

    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    lim_x_pos = (width - cx) / fx + 0.3 * tan_fovx
    lim_x_neg = cx / fx + 0.3 * tan_fovx
    lim_y_pos = (height - cy) / fy + 0.3 * tan_fovy
    lim_y_neg = cy / fy + 0.3 * tan_fovy
    tx = z_safe * torch.minimum(lim_x_pos, torch.maximum(-lim_x_neg, x / z_safe))
    ty = z_safe * torch.minimum(lim_y_pos, torch.maximum(-lim_y_neg, y / z_safe))
    zero = torch.zeros_like(z_safe)
    J = torch.stack(
        [fx / z_safe, zero, -fx * tx / z_safe**2, zero, fy / z_safe, -fy * ty / z_safe**2], dim=-1
    ).reshape(-1, 2, 3)
    cov2d = J @ cov_cam @ J.transpose(1, 2)  # [N, 2, 2]
    ca = cov2d[:, 0, 0] + eps2d
    cb = cov2d[:, 0, 1]
    cc = cov2d[:, 1, 1] + eps2d
    det = ca * cc - cb * cb
    valid = valid & (det > 0)
    det_safe = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([cc / det_safe, -cb / det_safe, ca / det_safe], dim=-1)
    means2d = torch.stack([fx * x / z_safe + cx, fy * y / z_safe + cy], dim=-1)

    with torch.no_grad():
        # alpha >= alpha_min  <=>  d^T conic d <= 2 log(o / alpha_min); the ellipse's bounding
        # box has half-widths sqrt(2 log(o / alpha_min) * Sigma_xx) (and _yy).
        level = 2.0 * torch.log(opacities.detach().clamp_min(1e-30) / alpha_min)
        valid = valid & (level > 0) & torch.isfinite(means2d).all(-1)
        level = level.clamp_min(0.0)
        half_extent = torch.stack([torch.sqrt(level * ca.clamp_min(0)), torch.sqrt(level * cc.clamp_min(0))], -1)
    return Projection(means2d, conics, z, half_extent, valid)


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


@torch.no_grad()
def bin_gaussians(
    means2d: Tensor,  # [N, 2]
    half_extent: Tensor,  # [N, 2]
    depths: Tensor,  # [N]
    valid: Tensor,  # [N] bool
    width: int,
    height: int,
    tile_size: int = 8,
) -> Bins:
    """Assign depth-sorted Gaussians to the tiles whose pixel centres their box covers."""
    device = means2d.device
    tiles_x = -(-width // tile_size)
    tiles_y = -(-height // tile_size)
    m = means2d.detach()
    # A tiny margin so float rounding never drops a pixel the reference would keep.
    h = half_extent + 1e-3
    # Pixel index i has its centre at i + 0.5; covered pixels: ceil(m - h - .5) .. floor(m + h - .5).
    lo = torch.ceil(m - h - 0.5)
    hi = torch.floor(m + h - 0.5)
    size = torch.tensor([width, height], device=device, dtype=m.dtype)
    lo = torch.maximum(lo, torch.zeros_like(lo))
    hi = torch.minimum(hi, size - 1)
    ok = valid & (lo <= hi).all(-1)
    lo = torch.where(ok[:, None], lo, torch.zeros_like(lo)).long() // tile_size  # [N, 2] tiles
    hi = torch.where(ok[:, None], hi, torch.zeros_like(hi)).long() // tile_size
    span = hi - lo + 1  # [N, 2]
    counts = torch.where(ok, span[:, 0] * span[:, 1], torch.zeros_like(span[:, 0]))  # [N]

    # Depth order; Gaussians generated in that order keep it after a stable sort by tile.
    order = torch.argsort(torch.where(ok, depths.detach(), torch.full_like(depths, math.inf)), stable=True)
    order = order[: int(ok.sum())]
    c = counts[order]
    total = int(c.sum())
    gid = torch.repeat_interleave(order, c)  # [M]
    first = torch.cumsum(c, 0) - c
    local = torch.arange(total, device=device) - torch.repeat_interleave(first, c)
    sx = span[gid, 0]
    tx = lo[gid, 0] + local % sx
    ty = lo[gid, 1] + local // sx
    tile = ty * tiles_x + tx
    tile, perm = torch.sort(tile, stable=True)
    gid = gid[perm]
    n_tiles = tiles_x * tiles_y
    tile_len = torch.bincount(tile, minlength=n_tiles)
    tile_start = torch.cumsum(tile_len, 0) - tile_len
    radii = torch.where(ok, torch.ceil(half_extent.max(-1).values), torch.zeros_like(depths)).to(torch.int32)
    return Bins(gid, tile, tile_start, tile_len, tiles_x, tiles_y, tile_size, radii)


def pair_coefficients(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    bins: Bins,
) -> Tensor:  # [M, 6]
    """``log alpha`` of pair (tile, g) at offset (u, v) from the tile centre = [1,u,v,u²,uv,v²]·k.

    Working relative to the tile centre keeps the polynomial well conditioned in float32."""
    g = bins.pair_gid
    ts = bins.tile_size
    ocx = (bins.pair_tile % bins.tiles_x).to(means2d.dtype) * ts + 0.5 * ts
    ocy = (bins.pair_tile // bins.tiles_x).to(means2d.dtype) * ts + 0.5 * ts
    m = means2d[g]
    dx = ocx - m[:, 0]
    dy = ocy - m[:, 1]
    a, b, c = conics[g].unbind(-1)
    logo = torch.log(opacities[g])
    return torch.stack(
        [
            logo - 0.5 * a * dx * dx - b * dx * dy - 0.5 * c * dy * dy,
            -a * dx - b * dy,
            -b * dx - c * dy,
            -0.5 * a,
            -b,
            -0.5 * c,
        ],
        dim=-1,
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
        self.batches = list(torch.split(self.tiles, per))


def _gather_batch(kp: Tensor, bins: Bins, tiles: Tensor):
    """Pad the pair lists of a batch of tiles to a common length.

    Returns pos [B, L] (pair index, clamped), pad [B, L] bool (True = padding), lens [B]."""
    lens = bins.tile_len[tiles]
    L = int(lens.max())
    ar = torch.arange(L, device=kp.device)
    pad = ar[None, :] >= lens[:, None]
    pos = (bins.tile_start[tiles][:, None] + ar[None, :]).clamp(max=max(kp.shape[0] - 1, 0))
    return pos, pad, lens


def _padded_coefficients(kp: Tensor, pos: Tensor, pad: Tensor) -> Tensor:  # [B, L, 6]
    """Coefficients of a batch; padding rows get log alpha = -1e4 everywhere (alpha 0)."""
    kb = kp.detach()[pos].masked_fill_(pad[..., None], 0.0)
    kb[..., 0].masked_fill_(pad, -1e4)
    return kb


def _thresholds(cfg: CompositeConfig, dtype: torch.dtype) -> tuple[float, float, float, float]:
    """log alpha_min, log alpha_clamp, and the largest values below alpha_min and
    transmittance_min, so that ``F.threshold(x, t, 0)`` keeps exactly ``x >= limit``."""
    def below(v: float) -> float:
        return float(torch.nextafter(torch.tensor(v, dtype=dtype), torch.tensor(0.0, dtype=dtype)))

    return math.log(cfg.alpha_min), math.log(cfg.alpha_clamp), below(cfg.alpha_min), below(cfg.transmittance_min)


def _chunk(kc: Tensor, P: Tensor, T: Tensor, cfg: CompositeConfig, for_backward: bool = False):
    """Blending of one chunk of ``k`` Gaussians over a batch of ``b`` tiles of ``p`` pixels.

    kc [b, k, 6] pair coefficients (padding rows give log alpha = -1e4), P [p, 6] pixel basis,
    T [b, p] transmittance entering the chunk; 0 marks a pixel that has stopped.

    Returns w [b, p, k] blending weights, T_next [b, p, k] transmittance after each Gaussian
    (0 from the first Gaussian that is not blended on), and for the backward pass also
    ``odds`` = alpha / (1 - alpha), zeroed where alpha does not depend smoothly on k
    (cut, clamped, or not blended).

    Weights use w_i = alpha_i T_i = T_next_i * alpha_i / (1 - alpha_i), which needs no
    exclusive cumprod; ``1 - alpha >= 1 - alpha_clamp > 0`` keeps the division safe."""
    log_min, log_clamp, alpha_cut, t_cut = _thresholds(cfg, kc.dtype)
    la = torch.matmul(P, kc.transpose(1, 2))  # [b, p, k] log alpha
    clamped = (la >= log_clamp) if for_backward else None
    # Clamp below before exp: the slow denormal path of exp is avoided and the clamp at
    # log_min - 1 lands under the cut, which then zeroes it.
    alpha = la.clamp_(min=log_min - 1.0, max=log_clamp).exp_()
    F.threshold_(alpha, alpha_cut, 0.0)
    one_m = 1.0 - alpha
    odds = alpha.div_(one_m)  # alpha is not needed any more
    T_next = one_m.cumprod_(2).mul_(T[:, :, None])
    # A pixel stops before the Gaussian that would take T below transmittance_min; T_next is
    # non-increasing, so zeroing it there zeroes every later weight too.
    F.threshold_(T_next, t_cut, 0.0)
    if not for_backward:
        return odds.mul_(T_next), T_next, None
    w = odds * T_next
    odds.masked_fill_(clamped | (T_next == 0), 0.0)
    return w, T_next, odds


class _Composite(torch.autograd.Function):
    """Tile compositing. Input ``aug`` [N, D] holds each Gaussian's features with two extra
    columns, z and 1, so that one bmm yields features, the depth sum and alpha = sum w."""

    @staticmethod
    def forward(ctx, kp: Tensor, aug: Tensor, bins: Bins, cfg: CompositeConfig):
        # kp [M, 6], aug [N, D] -> per-tile sums [tiles, p, D]
        device, dtype = aug.device, aug.dtype
        n_tiles = bins.tiles_x * bins.tiles_y
        p = bins.tile_size**2
        D = aug.shape[1]
        P = _pixel_basis(bins.tile_size, dtype, device)
        out = torch.zeros(n_tiles, p, D, dtype=dtype, device=device)
        evaluated = 0
        for tiles in _Schedule(bins, cfg).batches:
            pos, pad, lens = _gather_batch(kp, bins, tiles)
            kb = _padded_coefficients(kp, pos, pad)  # [B, L, 6]
            gb = bins.pair_gid[pos]  # [B, L]
            B = tiles.shape[0]
            act = torch.arange(B, device=device)  # batch rows still being composited
            T = torch.ones(B, p, dtype=dtype, device=device)
            acc = torch.zeros(B, p, D, dtype=dtype, device=device)
            for c0 in range(0, kb.shape[1], cfg.chunk):
                kc = kb[act, c0 : c0 + cfg.chunk]
                w, T_next, _ = _chunk(kc, P, T, cfg)
                acc.baddbmm_(w, aug[gb[act, c0 : c0 + cfg.chunk]])
                evaluated += w.numel()
                T = T_next[:, :, -1]
                finished = (T.amax(1) == 0) | (lens[act] <= c0 + cfg.chunk)
                if bool(finished.any()):
                    out[tiles[act[finished]]] = acc[finished]
                    keep = ~finished
                    act, T, acc = act[keep], T[keep], acc[keep]
                    if act.numel() == 0:
                        break
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
        kp, aug, out = ctx.saved_tensors
        bins, cfg = ctx.bins, ctx.cfg
        device, dtype = aug.device, aug.dtype
        p = bins.tile_size**2
        P = _pixel_basis(bins.tile_size, dtype, device)
        g_kp = torch.zeros_like(kp)
        g_aug = torch.zeros_like(aug)
        g_out = g_out.contiguous()
        total_all = (out * g_out).sum(-1)  # [tiles, p]
        for tiles in _Schedule(bins, cfg).batches:
            pos, pad, lens = _gather_batch(kp, bins, tiles)
            kb = _padded_coefficients(kp, pos, pad)
            gb = bins.pair_gid[pos]
            B = tiles.shape[0]
            gkb = torch.zeros_like(kb)
            act = torch.arange(B, device=device)
            T = torch.ones(B, p, dtype=dtype, device=device)
            g = g_out[tiles]  # [B, p, D]
            base = -total_all[tiles]  # prefix - total, [B, p]
            for c0 in range(0, kb.shape[1], cfg.chunk):
                kc = kb[act, c0 : c0 + cfg.chunk]
                gc = gb[act, c0 : c0 + cfg.chunk]
                w, T_next, odds = _chunk(kc, P, T, cfg, for_backward=True)
                f = aug[gc]  # [b, k, D]
                fg = torch.bmm(g, f.transpose(1, 2))  # [b, p, k]
                cs = torch.cumsum(w * fg, dim=2)
                inner = fg.mul_(T_next).add_(cs).add_(base[:, :, None])
                d_la = inner.mul_(odds)  # dL/d(log alpha) = alpha dL/dalpha
                gkb[act, c0 : c0 + cfg.chunk] = torch.matmul(d_la.transpose(1, 2), P)
                g_aug.index_add_(0, gc.reshape(-1), torch.bmm(w.transpose(1, 2), g).reshape(-1, aug.shape[1]))
                base = base + cs[:, :, -1]
                T = T_next[:, :, -1]
                finished = (T.amax(1) == 0) | (lens[act] <= c0 + cfg.chunk)
                if bool(finished.any()):
                    keep = ~finished
                    act, T, g, base = act[keep], T[keep], g[keep], base[keep]
                    if act.numel() == 0:
                        break
            sel = ~pad
            g_kp[pos[sel]] = gkb[sel]
        return g_kp, g_aug, None, None


def _untile(x: Tensor, bins: Bins, width: int, height: int) -> Tensor:
    """[tiles, p, C] -> [H, W, C]."""
    ts = bins.tile_size
    C = x.shape[-1]
    img = x.reshape(bins.tiles_y, bins.tiles_x, ts, ts, C).permute(0, 2, 1, 3, 4)
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
) -> dict:
    """Rasterize with the pure-PyTorch backend.

    Returns a dict: features [H, W, C], alpha [H, W, 1], depth_sum [H, W, 1] (sum w_i z_i,
    not normalised), means2d [N, 2], radii [N] int32, n_pairs (int, pixel-Gaussian pairs the
    forward compositing evaluated, padding included, early-stopped tiles not; for benchmarks)."""
    proj = project_gaussians(means, quats, scales, opacities, viewmat, K, width, height,
                             near=near, far=far, eps2d=eps2d, alpha_min=alpha_min)
    bins = bin_gaussians(proj.means2d, proj.half_extent, proj.depths, proj.valid, width, height, tile_size)
    kp = pair_coefficients(proj.means2d, proj.conics, opacities, bins)
    cfg = CompositeConfig(alpha_clamp=alpha_clamp, alpha_min=alpha_min,
                          transmittance_min=transmittance_min, chunk=chunk,
                          batch_elements=batch_elements)
    ones = torch.ones_like(proj.depths)[:, None]
    aug = torch.cat([features, proj.depths[:, None], ones], dim=1)  # [N, C + 2]
    out = _untile(_Composite.apply(kp, aug, bins, cfg), bins, width, height)  # [H, W, C + 2]
    C = features.shape[1]
    return {
        "features": out[..., :C],
        "alpha": out[..., C + 1 :],
        "depth_sum": out[..., C : C + 1],
        "means2d": proj.means2d,
        "radii": bins.radii,
        "n_pairs": bins.evaluated,
    }
