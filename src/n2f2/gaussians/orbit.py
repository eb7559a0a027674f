"""Cameras around a set of Gaussians that came without their capture's poses (a PLY trained
elsewhere): a ring of views looking at the Gaussians' centre, framed to their robust size."""

from __future__ import annotations

import math

import numpy as np
import torch

from ..cameras import Camera, look_at
from .model import Gaussians


def robust_center_radius(
    means: np.ndarray,  # [N, 3]
    opacities: np.ndarray,  # [N]
    quantile: float = 0.95,
) -> tuple[np.ndarray, float]:
    """Per-axis median of the Gaussians with opacity >= 0.5 (all of them if fewer than 10), and
    the ``quantile`` of their distances from it: stray floaters move neither."""
    solid = means[opacities >= 0.5]
    if len(solid) < 10:
        solid = means
    center = np.median(solid, axis=0)
    radius = float(np.quantile(np.linalg.norm(solid - center, axis=1), quantile))
    return center, max(radius, 1e-6)


def orbit_cameras(
    gaussians: Gaussians,
    num_views: int = 8,
    elevation: float = 20.0,  # degrees above the plane normal to ``up``
    up: tuple[float, float, float] = (0.0, -1.0, 0.0),  # world up; COLMAP worlds are usually y-down
    width: int = 512,
    height: int = 384,
    fov: float = 50.0,  # horizontal field of view, degrees
    margin: float = 1.15,  # the robust sphere fills 1 / margin of the smaller image side
) -> list[Camera]:
    """``num_views`` cameras evenly spaced in azimuth at ``elevation``, all looking at the
    Gaussians' robust centre from the distance at which their robust sphere fits the view."""
    if num_views < 1:
        raise ValueError(f"num_views must be >= 1, got {num_views}")
    means = gaussians.means.detach().cpu().numpy().astype(np.float64)
    opac = gaussians.opacities.detach().cpu().numpy()
    center, radius = robust_center_radius(means, opac)
    up_v = np.asarray(up, dtype=np.float64)
    if not np.isfinite(up_v).all() or np.linalg.norm(up_v) < 1e-9:
        raise ValueError(f"up must be a non-zero vector, got {up}")
    up_v /= np.linalg.norm(up_v)
    fx = 0.5 * width / math.tan(math.radians(fov) / 2)
    half = 0.5 * min(width, height) / fx  # tan of the half-angle of the smaller side
    distance = margin * radius / math.sin(math.atan(half))
    a = np.cross(up_v, [1.0, 0.0, 0.0] if abs(up_v[0]) < 0.9 else [0.0, 0.0, 1.0])
    a /= np.linalg.norm(a)
    b = np.cross(up_v, a)
    el = math.radians(elevation)
    cameras = []
    for k in range(num_views):
        az = 2 * math.pi * k / num_views
        direction = math.cos(el) * (math.cos(az) * a + math.sin(az) * b) + math.sin(el) * up_v
        R, t = look_at(center + distance * direction, center, up_v)
        cameras.append(Camera(fx, fx, width / 2, height / 2, width, height, R=R, t=t))
    return cameras


@torch.no_grad()
def render_views(
    gaussians: Gaussians, cameras: list[Camera], background: tuple[float, float, float] = (1.0, 1.0, 1.0)
) -> list[np.ndarray]:
    """RGB renders ``[H, W, 3]`` float32 in [0, 1], one per camera (SH at the model's degree)."""
    from ..render import render_rgb

    out = []
    for cam in cameras:
        r = render_rgb(gaussians, cam, background=background)
        out.append(r.features.clamp(0, 1).cpu().numpy().astype(np.float32))
    return out
