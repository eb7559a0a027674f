"""Vectorised ray casting against the demo scenes' primitives: nearest hits, surface normals and
shadow rays, with per-object bounding-sphere culling."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from .model import DemoScene, Primitive

_EPS = 1e-7  # minimum ray parameter of a hit (metres along a unit-z ray)


def _solve_quadratic(a: np.ndarray, b: np.ndarray, c: np.ndarray):
    """Roots t1 <= t2 of a t^2 + b t + c = 0 (NaN where there are none). [N] each."""
    disc = b * b - 4 * a * c
    ok = disc >= 0
    sq = np.sqrt(np.where(ok, disc, 0.0))
    # numerically stable form: q = -(b + sign(b) sqrt(disc)) / 2, roots q / a and c / q
    q = -0.5 * (b + np.where(b >= 0, sq, -sq))
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = q / a
        r2 = c / q
    t1 = np.minimum(r1, r2)
    t2 = np.maximum(r1, r2)
    t1 = np.where(ok, t1, np.nan)
    t2 = np.where(ok, t2, np.nan)
    return t1, t2


def _nearest(*candidates: np.ndarray) -> np.ndarray:
    """Smallest candidate > _EPS per ray (inf if none). NaN means no candidate."""
    out = None
    for c in candidates:
        c = np.where(np.isfinite(c) & (c > _EPS), c, np.inf)
        out = c if out is None else np.minimum(out, c)
    assert out is not None  # every caller passes at least one candidate
    return out


def intersect(
    prim: Primitive,
    origins: np.ndarray,  # [N, 3] or [1, 3] (shared) world
    dirs: np.ndarray,  # [N, 3] world (any length; t is in units of |dir|)
) -> np.ndarray:  # [N] ray parameter of the nearest hit > eps, inf if none
    """Nearest intersection of rays ``o + t d`` with a primitive (rays may start inside)."""
    if prim.kind == "plane":  # only the normal component matters
        normal = prim.rotation[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            return _nearest(((prim.center - origins) @ normal) / (dirs @ normal))
    o = (origins - prim.center) @ prim.rotation  # [N|1, 3]
    d = dirs @ prim.rotation
    ox, oy, oz = o[:, 0], o[:, 1], o[:, 2]
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    s = prim.size
    with np.errstate(divide="ignore", invalid="ignore"):
        if prim.kind == "ellipsoid":
            r = np.asarray(s)
            os_, ds = o / r, d / r
            t1, t2 = _solve_quadratic((ds * ds).sum(1), 2 * (os_ * ds).sum(1), (os_ * os_).sum(1) - 1)
            return _nearest(t1, t2)
        if prim.kind == "box":
            h = np.asarray(s)
            inv = 1.0 / d
            ta = (-h - o) * inv
            tb = (h - o) * inv
            tmin = np.nanmax(np.minimum(ta, tb), axis=1)
            tmax = np.nanmin(np.maximum(ta, tb), axis=1)
            hit = tmax >= tmin
            return _nearest(np.where(hit, tmin, np.nan), np.where(hit, tmax, np.nan))
        if prim.kind == "cylinder":
            r, hh = s
            rb = rt = r
        elif prim.kind == "cone":
            rb, rt, hh = s
        else:
            raise ValueError(f"unknown primitive kind {prim.kind!r}")
        # side: x^2 + y^2 = (rm + k z)^2 for |z| <= hh (a cylinder has k = 0)
        rm, k = 0.5 * (rb + rt), (rt - rb) / (2 * hh)
        rz = rm + k * oz
        a = dx * dx + dy * dy - (k * dz) ** 2
        bq = 2 * (ox * dx + oy * dy - k * dz * rz)
        c = ox * ox + oy * oy - rz * rz
        t1, t2 = _solve_quadratic(a, bq, c)
        side = []
        for t in (t1, t2):
            z = oz + t * dz
            side.append(np.where(np.abs(z) <= hh, t, np.nan))
        caps = []
        for zc, rc in ((-hh, rb), (hh, rt)):
            t = (zc - oz) / dz
            x, y = ox + t * dx, oy + t * dy
            caps.append(np.where(x * x + y * y <= rc * rc, t, np.nan))
        return _nearest(*side, *caps)


def local_normals(prim: Primitive, pl: np.ndarray) -> np.ndarray:
    """Outward unit normals [N, 3] (local frame) at local surface points ``pl`` [N, 3]."""
    s = prim.size
    if prim.kind == "plane":
        n = np.zeros_like(pl)
        n[:, 2] = 1.0
        return n
    if prim.kind == "ellipsoid":
        n = pl / np.asarray(s) ** 2
    elif prim.kind == "box":
        h = np.asarray(s)
        rel = np.abs(pl) / h
        axis = np.argmax(rel, axis=1)
        n = np.zeros_like(pl)
        n[np.arange(len(pl)), axis] = np.sign(pl[np.arange(len(pl)), axis])
    else:
        if prim.kind == "cylinder":
            rb = rt = s[0]
            hh = s[1]
        else:
            rb, rt, hh = s
        k = (rt - rb) / (2 * hh)
        rz = 0.5 * (rb + rt) + k * pl[:, 2]
        rho = np.sqrt(pl[:, 0] ** 2 + pl[:, 1] ** 2)
        side_n = np.stack([pl[:, 0], pl[:, 1], -k * rz], 1)
        on_cap = np.abs(np.abs(pl[:, 2]) - hh) < np.abs(rho - rz)
        cap_n = np.zeros_like(pl)
        cap_n[:, 2] = np.sign(pl[:, 2])
        n = np.where(on_cap[:, None], cap_n, side_n)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


@dataclass
class _Cluster:
    """Primitives of one object with a bounding sphere (planes: unbounded)."""

    indices: list[int]
    center: Optional[np.ndarray]  # [3]; None = never culled
    radius: float


def _clusters(prims: Sequence[Primitive], shadow_only: bool = False) -> list[_Cluster]:
    out: list[_Cluster] = []
    by_obj: dict[int, list[int]] = {}
    for i, p in enumerate(prims):
        if shadow_only and not p.casts_shadow:
            continue
        if p.kind == "plane":
            out.append(_Cluster([i], None, math.inf))
        else:
            by_obj.setdefault(p.object, []).append(i)
    for idx in by_obj.values():
        centers = np.stack([prims[i].center for i in idx])
        c = centers.mean(axis=0)
        r = max(float(np.linalg.norm(prims[i].center - c)) + prims[i].bounding_radius() for i in idx)
        out.append(_Cluster(idx, c, r * 1.0001))
    return out


def _sphere_candidates(
    center: np.ndarray,
    radius: float,
    origins: np.ndarray,  # [N, 3]
    dirs: np.ndarray,  # [N, 3]
    t_best: np.ndarray,  # [N]
) -> np.ndarray:  # [M] indices of rays that may hit inside the sphere
    oc = origins - center
    a = (dirs * dirs).sum(1)
    bh = (oc * dirs).sum(1)
    c = (oc * oc).sum(1) - radius * radius
    disc = bh * bh - a * c
    sq = np.sqrt(np.maximum(disc, 0.0))
    t_near = (-bh - sq) / a
    t_far = (-bh + sq) / a
    return np.nonzero((disc >= 0) & (t_far > _EPS) & (t_near < t_best))[0]


def trace(
    scene: DemoScene,
    origins: np.ndarray,  # [N, 3], or [3] shared by all rays
    dirs: np.ndarray,  # [N, 3]
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hit of each ray: ray parameter t [N] (inf if none) and primitive index [N]
    (-1 if none)."""
    dirs = np.asarray(dirs, dtype=np.float64)
    origins = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    shared = len(origins) == 1  # primary rays: keep one origin and let broadcasting work
    n = len(dirs)
    t_best = np.full(n, np.inf)
    p_best = np.full(n, -1, dtype=np.int64)
    for cl in _clusters(scene.primitives):
        if cl.center is None:  # unbounded (planes): every ray, no gather / scatter
            for i in cl.indices:
                t = intersect(scene.primitives[i], origins, dirs)
                better = t < t_best
                t_best[better] = t[better]
                p_best[better] = i
            continue
        sel = _sphere_candidates(cl.center, cl.radius, origins, dirs, t_best)
        if len(sel) == 0:
            continue
        o_s, d_s = (origins if shared else origins[sel]), dirs[sel]
        for i in cl.indices:
            t = intersect(scene.primitives[i], o_s, d_s)
            better = t < t_best[sel]
            t_best[sel[better]] = t[better]
            p_best[sel[better]] = i
    return t_best, p_best


def occluded(
    scene: DemoScene,
    origins: np.ndarray,  # [N, 3]
    direction: np.ndarray,  # [3] unit vector towards a directional light
) -> np.ndarray:  # [N] bool
    """Whether anything that casts shadows lies between each origin and the light."""
    dirs = np.broadcast_to(direction, origins.shape)
    blocked = np.zeros(len(origins), dtype=bool)
    far = np.full(len(origins), np.inf)
    for cl in _clusters(scene.primitives, shadow_only=True):
        if cl.center is None:
            sel = np.arange(len(origins))
        else:
            sel = _sphere_candidates(cl.center, cl.radius, origins, dirs, far)
        sel = sel[~blocked[sel]]
        if len(sel) == 0:
            continue
        hit = np.zeros(len(sel), dtype=bool)
        for i in cl.indices:
            hit |= np.isfinite(intersect(scene.primitives[i], origins[sel], dirs[sel]))
        blocked[sel[hit]] = True
    return blocked
