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


def _chunk_weights(kc: Tensor, P: Tensor, T: Tensor, done: Tensor, cfg: CompositeConfig):
    """Alpha, blending weights and the carried state for one chunk.

    kc [b, k, 6] (padding rows have a huge negative constant), P [p, 6], T [b, p], done [b, p].
    Returns alpha [b, p, k], grad_mask [b, p, k] (alpha depends smoothly on k), weights w,
    transmittance before each Gaussian T_before [b, p, k], T_new [b, p], done_new [b, p]."""
    la = torch.matmul(P, kc.transpose(1, 2))  # [b, p, k] log alpha
    log_clamp = math.log(cfg.alpha_clamp)
    log_min = math.log(cfg.alpha_min)
    live = la >= log_min
    # Clamping before exp avoids the slow denormal path and applies the alpha clamp.
    alpha = torch.exp(la.clamp(min=log_min, max=log_clamp)) * live
    one_m = 1.0 - alpha
    cp = torch.cumprod(one_m, dim=2)  # inclusive
    T_next = T[:, :, None] * cp
    valid = (T_next >= cfg.transmittance_min) & ~done[:, :, None]  # a prefix of the chunk
    T_before = T[:, :, None] * F.pad(cp[:, :, :-1], (1, 0), value=1.0)
    keep = live & valid
    w = alpha * T_before * keep
    # T after the last blended Gaussian of the chunk (valid is a prefix, so count it).
    n = valid.sum(2, keepdim=True)
    T_last = torch.gather(T_next, 2, (n - 1).clamp_min(0)).squeeze(2)
    T_new = torch.where(n.squeeze(2) > 0, T_last, T)
    done_new = done | (T_next[:, :, -1] < cfg.transmittance_min)
    grad_mask = keep & (la < log_clamp)
    return alpha, grad_mask, w, T_before, T_new, done_new


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(ctx, kp: Tensor, features: Tensor, depths: Tensor, bins: Bins, cfg: CompositeConfig):
        # kp [M, 6], features [N, C], depths [N] -> tile images [T, p, C], [T, p] depth sums, [T, p] T
        device, dtype = features.device, features.dtype
        n_tiles = bins.tiles_x * bins.tiles_y
        p = bins.tile_size**2
        C = features.shape[1]
        P = _pixel_basis(bins.tile_size, dtype, device)
        out = torch.zeros(n_tiles, p, C, dtype=dtype, device=device)
        out_d = torch.zeros(n_tiles, p, dtype=dtype, device=device)
        out_T = torch.ones(n_tiles, p, dtype=dtype, device=device)
        sched = _Schedule(bins, cfg)
        evaluated = 0
        for tiles in sched.batches:
            pos, pad, lens = _gather_batch(kp, bins, tiles)
            kb = _padded_coefficients(kp, pos, pad)  # [B, L, 6]
            gb = bins.pair_gid[pos]  # [B, L]
            B = tiles.shape[0]
            act = torch.arange(B, device=device)
            T = torch.ones(B, p, dtype=dtype, device=device)
            done = torch.zeros(B, p, dtype=torch.bool, device=device)
            acc = torch.zeros(B, p, C, dtype=dtype, device=device)
            acc_d = torch.zeros(B, p, dtype=dtype, device=device)
            for c0 in range(0, kb.shape[1], cfg.chunk):
                kc = kb[act, c0 : c0 + cfg.chunk]
                gc = gb[act, c0 : c0 + cfg.chunk]
                _, _, w, _, T, done = _chunk_weights(kc, P, T, done, cfg)
                evaluated += kc.shape[0] * kc.shape[1] * p
                acc += torch.bmm(w, features[gc])
                acc_d += (w * depths[gc][:, None, :]).sum(2)
                finished = done.all(1) | (lens[act] <= c0 + cfg.chunk)
                if bool(finished.any()):
                    tid = tiles[act[finished]]
                    out[tid], out_d[tid], out_T[tid] = acc[finished], acc_d[finished], T[finished]
                    keep = ~finished
                    act, T, done, acc, acc_d = act[keep], T[keep], done[keep], acc[keep], acc_d[keep]
                    if act.numel() == 0:
                        break
        bins.evaluated = evaluated
        ctx.bins, ctx.cfg = bins, cfg
        ctx.save_for_backward(kp, features, depths, out, out_d, out_T)
        return out, out_d, out_T

    @staticmethod
    def backward(ctx, g_out: Tensor, g_d: Tensor, g_T: Tensor):
        kp, features, depths, out, out_d, out_T = ctx.saved_tensors
        bins, cfg = ctx.bins, ctx.cfg
        device, dtype = features.device, features.dtype
        p = bins.tile_size**2
        P = _pixel_basis(bins.tile_size, dtype, device)
        g_kp = torch.zeros_like(kp)
        g_feat = torch.zeros_like(features)
        g_depth = torch.zeros_like(depths)
        g_out = g_out.contiguous()
        # Per pixel: total = sum_j w_j (f_j . g) over every blended Gaussian.
        total_all = (out * g_out).sum(-1) + out_d * g_d
        sched = _Schedule(bins, cfg)
        for tiles in sched.batches:
            pos, pad, lens = _gather_batch(kp, bins, tiles)
            kb = _padded_coefficients(kp, pos, pad)
            gb = bins.pair_gid[pos]
            B = tiles.shape[0]
            gkb = torch.zeros_like(kb)
            act = torch.arange(B, device=device)
            T = torch.ones(B, p, dtype=dtype, device=device)
            done = torch.zeros(B, p, dtype=torch.bool, device=device)
            prefix = torch.zeros(B, p, dtype=dtype, device=device)
            g_img, g_dep = g_out[tiles], g_d[tiles]  # [B, p, C], [B, p]
            total = total_all[tiles]
            # d alpha_out / d alpha_i = T_final / (1 - alpha_i); alpha_out = 1 - T_final.
            t_fin = out_T[tiles] * g_T[tiles]  # [B, p] (g_T is dL/dT_final)
            for c0 in range(0, kb.shape[1], cfg.chunk):
                kc = kb[act, c0 : c0 + cfg.chunk]
                gc = gb[act, c0 : c0 + cfg.chunk]
                alpha, gmask, w, T_before, T, done = _chunk_weights(kc, P, T, done, cfg)
                f = features[gc]  # [b, k, C]
                z = depths[gc]  # [b, k]
                fg = torch.bmm(g_img, f.transpose(1, 2)) + g_dep[:, :, None] * z[:, None, :]  # [b, p, k]
                cum = prefix[:, :, None] + torch.cumsum(w * fg, dim=2)
                after = total[:, :, None] - cum  # sum over blended Gaussians behind i
                # dL/dalpha_i = T_i (f_i.g) - (sum_{j>i} w_j f_j.g) / (1 - a_i) + dL/dT_fin * dT_fin/da_i
                d_alpha = T_before * fg - (after + t_fin[:, :, None]) / (1.0 - alpha)
                d_la = d_alpha * alpha * gmask  # [b, p, k]
                gkb[act, c0 : c0 + cfg.chunk] = torch.matmul(d_la.transpose(1, 2), P)
                g_feat.index_add_(0, gc.reshape(-1), torch.bmm(w.transpose(1, 2), g_img).reshape(-1, f.shape[2]))
                g_depth.index_add_(0, gc.reshape(-1), (w * g_dep[:, :, None]).sum(1).reshape(-1))
                prefix = cum[:, :, -1]
                finished = done.all(1) | (lens[act] <= c0 + cfg.chunk)
                if bool(finished.any()):
                    keep = ~finished
                    act, T, done, prefix = act[keep], T[keep], done[keep], prefix[keep]
                    g_img, g_dep, total, t_fin = g_img[keep], g_dep[keep], total[keep], t_fin[keep]
                    if act.numel() == 0:
                        break
            sel = ~pad
            g_kp[pos[sel]] = gkb[sel]
        return g_kp, g_feat, g_depth, None, None


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
    out, out_d, out_T = _Composite.apply(kp, features, proj.depths, bins, cfg)
    return {
        "features": _untile(out, bins, width, height),
        "alpha": _untile(1.0 - out_T[..., None], bins, width, height),
        "depth_sum": _untile(out_d[..., None], bins, width, height),
        "means2d": proj.means2d,
        "radii": bins.radii,
        "n_pairs": bins.evaluated,
    }
