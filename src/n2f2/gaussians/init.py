"""Initial Gaussians: from sparse points (as 3DGS does from COLMAP's points3D) or at random
inside the camera frusta (for scenes without points)."""

from __future__ import annotations

import math
from typing import Callable, Optional, Sequence

import numpy as np
import torch

from ..cameras import Camera
from .model import Gaussians, inverse_sigmoid, num_sh_bases, rgb_to_sh

INIT_OPACITY = 0.1  # 3DGS create_from_pcd


def knn_scale(points: np.ndarray, k: int = 3) -> np.ndarray:  # [P, 3] -> [P]
    """sqrt(mean squared distance to the k nearest other points), 3DGS's ``distCUDA2`` scale.

    Clamped below (3DGS clamps the squared distance at 1e-7) so duplicate points do not get a
    zero (log -inf) scale."""
    from scipy.spatial import cKDTree  # pyright: ignore[reportAttributeAccessIssue]  # compiled, no stubs

    points = np.asarray(points, dtype=np.float64)
    p = len(points)
    if p < 2:
        return np.full(p, 1e-2)
    kk = min(k, p - 1)
    dist, _ = cKDTree(points).query(points, k=kk + 1)  # the first neighbour is the point itself
    dist = np.asarray(dist).reshape(p, kk + 1)[:, 1:]
    return np.sqrt(np.maximum((dist**2).mean(axis=1), 1e-7))


def init_from_points(
    points: np.ndarray,  # [P, 3] world positions
    colors: np.ndarray,  # [P, 3] uint8 RGB
    sh_degree: int = 3,  # max SH degree of the model; higher bands start at zero
    device: torch.device | str | None = None,
) -> Gaussians:
    """One isotropic Gaussian per point: scale = k-NN distance, opacity 0.1, identity rotation,
    DC colour from the point colour (3DGS ``create_from_pcd``). Active SH degree starts at 0."""
    points = np.asarray(points, dtype=np.float64)
    colors = np.asarray(colors)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) == 0:
        raise ValueError(f"points must be a non-empty [P, 3] array, got shape {points.shape}")
    if colors.shape != points.shape:
        raise ValueError(f"colors must be [P, 3] like points, got {colors.shape} vs {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError("points contain NaN or infinite coordinates")
    rgb = torch.as_tensor(colors.astype(np.float32) / 255.0)
    return _isotropic(
        torch.as_tensor(points, dtype=torch.float32),
        rgb,
        torch.as_tensor(knn_scale(points), dtype=torch.float32),
        sh_degree,
        device,
    )


def _in_image(camera: Camera, uv: np.ndarray, z: np.ndarray) -> np.ndarray:  # [M, 2], [M] -> [M] bool
    """In front of ``camera`` and inside its image."""
    return (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)


def uncovered_cells(
    points: np.ndarray,  # [P, 3] world
    camera: Camera,
    cells: int = 16,  # cells along the longer image side
) -> np.ndarray:  # [gh, gw] bool
    """The cells of a ``cells``-wide grid over the image that no point projects into: the parts
    of a view that sparse points miss (plain walls, backdrops, sky)."""
    size = max(camera.width, camera.height) / cells
    gw, gh = math.ceil(camera.width / size), math.ceil(camera.height / size)
    uv, z = camera.project(np.asarray(points, dtype=np.float64))
    ok = _in_image(camera, uv, z)
    covered = np.zeros((gh, gw), dtype=bool)
    covered[np.minimum((uv[ok, 1] / size).astype(int), gh - 1), np.minimum((uv[ok, 0] / size).astype(int), gw - 1)] = (
        True
    )
    return ~covered


def random_points_in_frusta(
    cameras: Sequence[Camera],
    n: int,  # number of points
    near: float,  # z-depth range the points are drawn from, in world units
    far: float,
    seed: int = 0,
    images: Optional[Callable[[int], np.ndarray]] = None,  # view index -> float [H, W, 3] in [0, 1]
    cells: Optional[Sequence[np.ndarray]] = None,  # per camera [gh, gw] bool: where to draw (a grid)
    shell: Optional[tuple[np.ndarray, float]] = None,  # (centre [3], radius): place points on this sphere
) -> tuple[np.ndarray, np.ndarray]:  # [n, 3] float64, [n, 3] uint8
    """``n`` points at random pixels of random cameras, at a z-depth uniform in [near, far].
    Each point takes the colour of the pixel it was drawn through when ``images`` is given
    (every view that sees it along that ray starts right), else a random colour. With
    ``cells``, pixels are drawn uniformly from the True cells of each camera's grid only, and
    cameras in proportion to their True cells. With ``shell``, each point is where its ray
    leaves that sphere instead (a background beyond every camera inside it)."""
    if n <= 0 or not cameras:
        raise ValueError("random_points_in_frusta needs n > 0 and at least one camera")
    if not 0 < near < far:
        raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
    rng = np.random.default_rng(seed)
    if cells is None:
        cam_ids = rng.integers(0, len(cameras), size=n)
    else:
        counts = np.array([c.sum() for c in cells], dtype=np.float64)
        if counts.sum() == 0:
            raise ValueError("random_points_in_frusta: no cell to draw from")
        cam_ids = rng.choice(len(cameras), size=n, p=counts / counts.sum())
    points = np.empty((n, 3))
    colors = (rng.random((n, 3)) * 255.0).astype(np.uint8)
    for ci in np.unique(cam_ids):  # vectorised per camera
        sel = np.nonzero(cam_ids == ci)[0]
        cam = cameras[ci]
        if cells is None:
            uv = rng.random((len(sel), 2)) * np.array([cam.width, cam.height])
        else:
            gh, gw = cells[ci].shape
            rows, cols = np.nonzero(cells[ci])
            pick = rng.integers(0, len(rows), size=len(sel))
            cell_wh = np.array([cam.width / gw, cam.height / gh])
            uv = (np.stack([cols[pick], rows[pick]], axis=1) + rng.random((len(sel), 2))) * cell_wh
        if shell is None:
            depth = near + (far - near) * rng.random(len(sel))
        else:
            depth = _sphere_exit_depth(cam, uv, *shell)
        points[sel] = cam.unproject(uv, depth)
        if images is not None:
            image = images(int(ci))
            rows = np.minimum((uv[:, 1] * image.shape[0] / cam.height).astype(int), image.shape[0] - 1)
            cols = np.minimum((uv[:, 0] * image.shape[1] / cam.width).astype(int), image.shape[1] - 1)
            colors[sel] = np.clip(image[rows, cols] * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return points, colors


def _sphere_exit_depth(
    camera: Camera,
    uv: np.ndarray,  # [M, 2] pixels
    center: np.ndarray,
    radius: float,
) -> np.ndarray:  # [M] z-depth
    """z-depth at which each pixel's ray leaves the sphere (the far root; the camera must be
    inside it, which ``background_shell`` guarantees)."""
    o = camera.center
    d = camera.unproject(uv, np.ones(len(uv))) - o  # [M, 3], z-depth 1 per unit of t
    oc = o - np.asarray(center, dtype=np.float64)
    a = (d * d).sum(1)
    b = 2.0 * d @ oc
    c = oc @ oc - radius * radius
    return (-b + np.sqrt(np.maximum(b * b - 4 * a * c, 0.0))) / (2 * a)


def background_shell(
    cameras: Sequence[Camera],
    points: Optional[np.ndarray] = None,  # [P, 3] sparse points, if any
) -> tuple[np.ndarray, float]:  # (centre [3], radius)
    """A sphere around the capture, twice as far from the cameras' centroid as the farthest
    camera (and the 95th percentile of the points): Gaussians on it sit behind everything from
    every camera, so they can stand for a backdrop without floating in front of another view
    (random depths along one view's rays land in front of the opposite views of an orbit)."""
    centers = np.stack([c.center for c in cameras])
    center = centers.mean(axis=0)
    radius = float(np.linalg.norm(centers - center, axis=1).max())
    if points is not None and len(points):
        radius = max(radius, float(np.percentile(np.linalg.norm(points - center, axis=1), 95)))
    return center, 2.0 * max(radius, 1e-6)


def clear_of_cameras(
    points: np.ndarray,  # [P, 3]
    cameras: Sequence[Camera],
    near: float,
    min_seen: float = 0.0,  # also needs to be inside this fraction of the views
) -> np.ndarray:  # [P] bool
    """False for points that some camera sees (inside its image) closer than z-depth ``near``,
    or that fewer than ``min_seen`` of the cameras see at all."""
    ok = np.ones(len(points), dtype=bool)
    seen = np.zeros(len(points))
    for cam in cameras:
        uv, z = cam.project(points)
        inside = _in_image(cam, uv, z)
        ok &= ~(inside & (z < near))
        seen += inside
    return ok & (seen >= min_seen * len(cameras))


def random_points_seen(
    cameras: Sequence[Camera],
    n: int,  # number of points
    near: float,  # z-depth range the points are drawn from, in world units
    far: float,
    seed: int = 0,
    images: Optional[Callable[[int], np.ndarray]] = None,  # view index -> float [H, W, 3] in [0, 1]
    min_seen: float = 0.0,  # keep points inside at least this fraction of the views
) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``n`` points of :func:`random_points_in_frusta` (and their colours), none closer
    than ``near`` to any camera that sees it and each seen by at least ``min_seen`` of the
    cameras: redrawn up to 16 times until enough are kept."""
    parts, colors, drawn = [], [], 0
    for attempt in range(16):  # draw, drop points near a camera or seen by few, repeat
        pts, cols = random_points_in_frusta(cameras, 4 * n, near, far, seed=seed + attempt, images=images)
        keep = clear_of_cameras(pts, cameras, near, min_seen)
        parts.append(pts[keep])
        colors.append(cols[keep])
        drawn += int(keep.sum())
        if drawn >= n:
            break
    return np.concatenate(parts)[:n], np.concatenate(colors)[:n]


def init_random_in_frusta(
    cameras: Sequence[Camera],
    n: int,  # number of Gaussians
    near: float,  # z-depth range the points are drawn from, in world units
    far: float,
    seed: int = 0,
    sh_degree: int = 3,
    device: torch.device | str | None = None,
    images: Optional[Callable[[int], np.ndarray]] = None,  # view index -> float [H, W, 3] in [0, 1]
    shell_fraction: float = 0.0,  # this fraction goes on the background_shell
    min_seen: float = 0.0,  # keep points inside at least this fraction of the views
) -> Gaussians:
    """``n`` Gaussians at :func:`random_points_seen` (pixel colours when ``images`` is
    given, else random ones), and ``shell_fraction`` of them on the :func:`background_shell`;
    scales and opacities as :func:`init_from_points`.

    ``min_seen`` keeps the draw where the views overlap (the middle of an orbit): points along
    one view's rays that few others see became a fog in front of the object on a real orbit
    capture (15.7 dB held-out after 1000 steps)."""
    n_shell = int(round(shell_fraction * n))
    points, cols = random_points_seen(cameras, n - n_shell, near, far, seed=seed, images=images, min_seen=min_seen)
    if n_shell:
        shell_pts, shell_cols = random_points_in_frusta(
            cameras, n_shell, near, far, seed=seed, images=images, shell=background_shell(cameras)
        )
        points, cols = np.concatenate([points, shell_pts]), np.concatenate([cols, shell_cols])
    return init_from_points(points, cols, sh_degree=sh_degree, device=device)


def _isotropic(
    means: torch.Tensor,  # [P, 3]
    rgb: torch.Tensor,  # [P, 3] in [0, 1]
    scale: torch.Tensor,  # [P]
    sh_degree: int,
    device,
) -> Gaussians:
    p = means.shape[0]
    sh = torch.zeros(p, num_sh_bases(sh_degree), 3)
    sh[:, 0, :] = rgb_to_sh(rgb)
    quats = torch.zeros(p, 4)
    quats[:, 0] = 1.0
    log_scales = torch.log(scale)[:, None].repeat(1, 3)
    opacity_logits = inverse_sigmoid(torch.full((p,), INIT_OPACITY))
    g = Gaussians(means, quats, log_scales, opacity_logits, sh, sh_degree=0)
    return g.to(device) if device is not None else g
