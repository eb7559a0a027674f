"""Procedural textures, Lambert + Blinn-Phong shading with a shadowed key light, and
:func:`render_view` (one supersampled view with depth, region ids and surface points)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...cameras import Camera
from .model import DemoScene, Material
from .raytrace import local_normals, occluded, trace


def _hash_float(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    """Deterministic integer hash of lattice coordinates -> float in [0, 1)."""
    h = np.full(ix.shape, (int(seed) * 0x9E3779B1 + 0x7F4A7C15) & 0xFFFFFFFF, dtype=np.uint32)
    for v, mult in ((ix, 0x85EBCA6B), (iy, 0xC2B2AE35), (iz, 0x27D4EB2F)):
        h ^= (v.astype(np.int64) & 0xFFFFFFFF).astype(np.uint32) * np.uint32(mult)
        h ^= h >> np.uint32(15)
        h *= np.uint32(0x2C1B3C6D)
        h ^= h >> np.uint32(12)
    h ^= h >> np.uint32(16)
    return h.astype(np.float64) / 4294967296.0


def value_noise(
    points: np.ndarray,  # [N, 3]
    freq: float,
    seed: int,
) -> np.ndarray:  # [N] in [0, 1]
    """Smooth 3D value noise (trilinear interpolation of hashed lattice values)."""
    q = points * freq
    i0 = np.floor(q)
    f = q - i0
    f = f * f * (3 - 2 * f)
    i0 = i0.astype(np.int64)
    out = np.zeros(len(points))
    for cx in (0, 1):
        wx = f[:, 0] if cx else 1 - f[:, 0]
        for cy in (0, 1):
            wy = f[:, 1] if cy else 1 - f[:, 1]
            for cz in (0, 1):
                wz = f[:, 2] if cz else 1 - f[:, 2]
                out += wx * wy * wz * _hash_float(i0[:, 0] + cx, i0[:, 1] + cy, i0[:, 2] + cz, seed)
    return out


def albedo(
    material: Material,
    pl: np.ndarray,  # [N, 3] local surface points
    seed: int,
) -> np.ndarray:  # [N, 3] in [0, 1]
    m = material
    c1 = np.asarray(m.color)
    c2 = np.asarray(m.color2)
    if m.pattern == "plain":
        w = np.zeros(len(pl))
    elif m.pattern == "checker":
        w = ((np.floor(pl[:, 0] / m.period) + np.floor(pl[:, 1] / m.period)) % 2).astype(np.float64)
    elif m.pattern == "stripes":
        w = ((pl[:, m.axis] / m.period) % 1.0 < m.duty).astype(np.float64)
    elif m.pattern == "dots":
        w = (value_noise(pl, 1.0 / m.period, seed + 101) > 1.0 - m.duty).astype(np.float64)
    elif m.pattern == "rim":
        w = (np.hypot(pl[:, 0], pl[:, 1]) > m.period).astype(np.float64)
    elif m.pattern == "planks":
        board = np.floor(pl[:, 1] / m.period)
        zeros = np.zeros_like(board, dtype=np.int64)
        shade = 0.8 + 0.4 * _hash_float(board.astype(np.int64), zeros, zeros, seed + 202)
        grain = 0.5 + 0.5 * np.sin(pl[:, 1] * 180.0 + 6.0 * value_noise(pl * [0.3, 1, 1], 8.0, seed + 203))
        w = 0.55 * grain**6
        gap = (pl[:, 1] / m.period) % 1.0 < 0.04
        w = np.where(gap, 1.0, w)
        col = (c1 * (1 - w[:, None]) + c2 * w[:, None]) * shade[:, None]
        return np.clip(col * _noise_factor(m, pl, seed)[:, None], 0, 1)
    else:
        raise ValueError(f"unknown texture pattern {m.pattern!r}")
    col = c1 * (1 - w[:, None]) + c2 * w[:, None]
    return np.clip(col * _noise_factor(m, pl, seed)[:, None], 0, 1)


def _noise_factor(m: Material, pl: np.ndarray, seed: int) -> np.ndarray:
    if m.noise <= 0:
        return np.ones(len(pl))
    return 1.0 + m.noise * (2.0 * value_noise(pl, m.noise_freq, seed + 303) - 1.0)


@dataclass
class ViewRender:
    rgb: np.ndarray  # [H, W, 3] float32 in [0, 1] (supersampled)
    depth: np.ndarray  # [H, W] float64 z-depth at pixel centres
    primitive: np.ndarray  # [H, W] int64 primitive index at pixel centres
    regions: np.ndarray  # [3, H, W] int32 (part, object, group) at pixel centres
    points: np.ndarray  # [H, W, 3] float64 world hit points at pixel centres


def render_view(
    scene: DemoScene, camera: Camera, supersample: int = 3, seed: int = 0, chunk: int = 16384
) -> ViewRender:
    """Ray-trace one view. ``supersample`` must be odd: the RGB is the mean of an
    ``s x s`` grid of samples per pixel whose middle sample is the pixel centre, where depth,
    ids and surface points are taken."""
    s = int(supersample)
    if s < 1 or s % 2 == 0:
        raise ValueError(f"supersample must be an odd positive integer, got {supersample}")
    H, W = camera.height, camera.width
    offs = (np.arange(s) + 0.5) / s  # middle one is exactly 0.5
    u = (np.arange(W)[:, None] + offs[None, :]).reshape(-1)  # [W*s]
    v = (np.arange(H)[:, None] + offs[None, :]).reshape(-1)  # [H*s]
    uu, vv = np.meshgrid(u, v)  # [H*s, W*s]
    d_cam = np.stack([(uu - camera.cx) / camera.fx, (vv - camera.cy) / camera.fy, np.ones_like(uu)], axis=-1).reshape(
        -1, 3
    )
    dirs = d_cam @ camera.R  # R^T d: camera z component stays 1, so t = z-depth
    origin = camera.center
    # Chunks of rays keep NumPy's temporaries in cache (about 2x faster than one big batch).
    n = len(dirs)
    t = np.empty(n)
    prim = np.empty(n, dtype=np.int64)
    rgb = np.empty((n, 3))
    for a in range(0, n, chunk):
        b_ = min(n, a + chunk)
        t[a:b_], prim[a:b_] = trace(scene, origin, dirs[a:b_])
        pts = origin + t[a:b_, None] * dirs[a:b_]
        if not np.isfinite(pts).all():
            raise RuntimeError("a ray left the room; the demo scene should be closed")
        rgb[a:b_] = _shade(scene, pts, dirs[a:b_], prim[a:b_], seed)
    points = origin + t[:, None] * dirs

    rgb = rgb.reshape(H, s, W, s, 3).mean(axis=(1, 3)).astype(np.float32)
    c = s // 2
    centre = lambda a: a.reshape(H, s, W, s, *a.shape[1:])[:, c, :, c]  # noqa: E731
    prim_c = centre(prim)
    ids = scene.id_table()[prim_c]  # [H, W, 3]
    return ViewRender(
        rgb=rgb,
        depth=centre(t),
        primitive=prim_c,
        regions=np.ascontiguousarray(ids.transpose(2, 0, 1)).astype(np.int32),
        points=centre(points),
    )


def _shade(
    scene: DemoScene,
    points: np.ndarray,  # [N, 3]
    dirs: np.ndarray,  # [N, 3]
    prim: np.ndarray,  # [N]
    seed: int,
) -> np.ndarray:  # [N, 3]
    n = len(points)
    normals = np.zeros((n, 3))
    base = np.zeros((n, 3))
    spec_w = np.zeros(n)
    order = np.argsort(prim, kind="stable")
    bounds = np.searchsorted(prim[order], np.arange(len(scene.primitives) + 1))
    for i, p in enumerate(scene.primitives):
        sel = order[bounds[i] : bounds[i + 1]]
        if len(sel) == 0:
            continue
        pl = p.to_local(points[sel])
        normals[sel] = local_normals(p, pl) @ p.rotation.T
        base[sel] = albedo(p.material, pl, seed)
        spec_w[sel] = p.material.specular
    view = -dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    # two-sided surfaces: the normal faces the viewer
    flip = (normals * view).sum(1) < 0
    normals[flip] *= -1
    key = scene.key_light
    ndl_key = normals @ key
    lit = ndl_key > 0
    shadow = np.zeros(n, dtype=bool)
    idx = np.nonzero(lit)[0]
    shadow[idx] = occluded(scene, points[idx] + 1e-5 * normals[idx], key)
    vis = (lit & ~shadow).astype(np.float64)
    ndl_fill = np.maximum(normals @ scene.fill_light, 0.0)
    light = scene.ambient + scene.key_intensity * np.maximum(ndl_key, 0) * vis + scene.fill_intensity * ndl_fill
    half = view + key
    half /= np.maximum(np.linalg.norm(half, axis=1, keepdims=True), 1e-12)
    spec = spec_w * np.maximum((normals * half).sum(1), 0.0) ** 40 * vis
    return np.clip(base * light[:, None] + spec[:, None], 0.0, 1.0)
