"""Initial Gaussians: from sparse points (as 3DGS does from COLMAP's points3D) or at random
inside the camera frusta (for scenes without points)."""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch

from ..cameras import Camera
from .model import Gaussians, inverse_sigmoid, num_sh_bases, rgb_to_sh

INIT_OPACITY = 0.1  # 3DGS create_from_pcd


def knn_scale(points: np.ndarray, k: int = 3) -> np.ndarray:  # [P, 3] -> [P]
    """sqrt(mean squared distance to the k nearest other points), 3DGS's ``distCUDA2`` scale.

    Clamped below (3DGS clamps the squared distance at 1e-7) so duplicate points do not get a
    zero (log -inf) scale."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    p = len(points)
    if p < 2:
        return np.full(p, 1e-2)
    kk = min(k, p - 1)
    dist, _ = cKDTree(points).query(points, k=kk + 1)  # the first neighbour is the point itself
    dist = np.asarray(dist).reshape(p, kk + 1)[:, 1:]
    return np.sqrt(np.maximum((dist ** 2).mean(axis=1), 1e-7))


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
    return _isotropic(torch.as_tensor(points, dtype=torch.float32), rgb,
                      torch.as_tensor(knn_scale(points), dtype=torch.float32), sh_degree, device)


def init_random_in_frusta(
    cameras: Sequence[Camera],
    n: int,  # number of Gaussians
    near: float,  # z-depth range the points are drawn from, in world units
    far: float,
    seed: int = 0,
    sh_degree: int = 3,
    device: torch.device | str | None = None,
) -> Gaussians:
    """``n`` Gaussians at random pixels of random cameras, at a z-depth uniform in [near, far],
    with random colours; scales and opacities as :func:`init_from_points`."""
    if n <= 0 or not cameras:
        raise ValueError("init_random_in_frusta needs n > 0 and at least one camera")
    if not 0 < near < far:
        raise ValueError(f"need 0 < near < far, got near={near}, far={far}")
    rng = np.random.default_rng(seed)
    cam_ids = rng.integers(0, len(cameras), size=n)
    points = np.empty((n, 3))
    for ci in np.unique(cam_ids):  # vectorised per camera
        sel = np.nonzero(cam_ids == ci)[0]
        cam = cameras[ci]
        uv = rng.random((len(sel), 2)) * np.array([cam.width, cam.height])
        depth = near + (far - near) * rng.random(len(sel))
        points[sel] = cam.unproject(uv, depth)
    colors = (rng.random((n, 3)) * 255.0).astype(np.uint8)
    return init_from_points(points, colors, sh_degree=sh_degree, device=device)


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
