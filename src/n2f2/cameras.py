"""The one camera convention of n2f2. Every other module trusts what is written here.

Convention (OpenCV / COLMAP):

* **Axes.** Camera space has x pointing right, y pointing down and z pointing forward
  (into the scene). A point is in front of the camera when its camera-space z > 0.
* **Extrinsics.** ``R`` and ``t`` map world to camera: ``x_cam = R @ x_world + t``.
  The camera centre in world space is ``-R.T @ t``.
* **Pixels.** Image coordinates are continuous, with the origin at the top-left *corner* of
  the top-left pixel; u grows to the right, v grows down. The centre of pixel (row j,
  column i) is at ``(u, v) = (i + 0.5, j + 0.5)``. Projection is
  ``u = fx * x / z + cx``, ``v = fy * y / z + cy``. (COLMAP, nerfstudio and gsplat all use
  this convention; a centred principal point is ``cx = width / 2``.)
* **Depth.** "Depth" everywhere in n2f2 means z-depth, the camera-space z coordinate, not the
  distance along the ray.
* **Other conventions.** OpenGL / nerfstudio / Blender camera-to-world matrices have x right,
  y up, z backward. They are converted here and nowhere else: :func:`from_opengl_c2w` and
  :meth:`Camera.opengl_c2w`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike

# Flips OpenCV camera axes to OpenGL camera axes (and back: it is its own inverse).
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0])


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: intrinsics and world-to-camera extrinsics (OpenCV axes)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    R: np.ndarray = field(default_factory=lambda: np.eye(3))  # [3, 3] world-to-camera rotation
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))  # [3] world-to-camera translation

    def __post_init__(self) -> None:
        R = np.asarray(self.R, dtype=np.float64)
        t = np.asarray(self.t, dtype=np.float64).reshape(-1)
        if R.shape != (3, 3):
            raise ValueError(f"camera rotation must be 3x3, got shape {R.shape}")
        if t.shape != (3,):
            raise ValueError(f"camera translation must have 3 entries, got shape {t.shape}")
        values = [self.fx, self.fy, self.cx, self.cy]
        if not (np.isfinite(R).all() and np.isfinite(t).all() and all(math.isfinite(v) for v in values)):
            raise ValueError("camera has NaN or infinite entries")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if abs(np.linalg.det(R) - 1.0) > 1e-3 or not np.allclose(R @ R.T, np.eye(3), atol=1e-3):
            raise ValueError("camera rotation is not a proper rotation matrix (R R^T != I or det != 1)")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "fx", float(self.fx))
        object.__setattr__(self, "fy", float(self.fy))
        object.__setattr__(self, "cx", float(self.cx))
        object.__setattr__(self, "cy", float(self.cy))

    # ----------------------------------------------------------------------------- matrices
    @property
    def K(self) -> np.ndarray:  # [3, 3]
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def world_to_camera(self) -> np.ndarray:  # [4, 4]
        m = np.eye(4)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m

    @property
    def camera_to_world(self) -> np.ndarray:  # [4, 4], OpenCV axes
        m = np.eye(4)
        m[:3, :3] = self.R.T
        m[:3, 3] = -self.R.T @ self.t
        return m

    @property
    def center(self) -> np.ndarray:  # [3] camera centre in world space
        return -self.R.T @ self.t

    def opengl_c2w(self) -> np.ndarray:  # [4, 4]
        """Camera-to-world with OpenGL axes (x right, y up, z backward), as nerfstudio writes."""
        m = self.camera_to_world
        m[:3, :3] = m[:3, :3] @ OPENCV_TO_OPENGL
        return m

    # ----------------------------------------------------------------------------- geometry
    def world_to_cam_points(self, points: np.ndarray) -> np.ndarray:
        """points [..., 3] world -> [..., 3] camera space."""
        return np.asarray(points, dtype=np.float64) @ self.R.T + self.t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points [..., 3] to continuous pixel coordinates [..., 2] (u, v) and
        z-depth [...]. Points behind the camera get z <= 0; their uv is not meaningful."""
        pc = self.world_to_cam_points(points)
        z = pc[..., 2]
        safe_z = np.where(np.abs(z) < 1e-12, 1e-12, z)
        u = self.fx * pc[..., 0] / safe_z + self.cx
        v = self.fy * pc[..., 1] / safe_z + self.cy
        return np.stack([u, v], axis=-1), z

    def unproject(self, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Continuous pixel coordinates [..., 2] and z-depth [...] -> world points [..., 3]."""
        uv = np.asarray(uv, dtype=np.float64)
        depth = np.asarray(depth, dtype=np.float64)
        x = (uv[..., 0] - self.cx) / self.fx * depth
        y = (uv[..., 1] - self.cy) / self.fy * depth
        pc = np.stack([x, y, depth], axis=-1)
        return (pc - self.t) @ self.R  # R^T (pc - t), row-vector form

    def pixel_centers(self) -> np.ndarray:
        """[H, W, 2] continuous (u, v) of every pixel centre."""
        u = np.arange(self.width) + 0.5
        v = np.arange(self.height) + 0.5
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu, vv], axis=-1)

    def ray_directions(self) -> np.ndarray:
        """[H, W, 3] world-space directions through pixel centres, scaled so that camera z = 1
        (so ``center + depth * dir`` is the point at that z-depth)."""
        uv = self.pixel_centers()
        d_cam = np.stack(
            [(uv[..., 0] - self.cx) / self.fx, (uv[..., 1] - self.cy) / self.fy, np.ones(uv.shape[:2])], axis=-1
        )
        return d_cam @ self.R  # R^T d

    def depth_to_points(self, depth: np.ndarray) -> np.ndarray:
        """z-depth image [H, W] -> world points [H, W, 3] at the pixel centres."""
        return self.center + depth[..., None] * self.ray_directions()

    # ----------------------------------------------------------------------------- resizing
    def scaled(self, width: int, height: int) -> "Camera":
        """The same camera for an image resized to ``width x height``.

        With pixel centres at +0.5, resizing scales continuous coordinates exactly, so
        fx, cx scale by width ratio and fy, cy by height ratio."""
        sx = width / self.width
        sy = height / self.height
        return replace(
            self,
            fx=self.fx * sx,
            fy=self.fy * sy,
            cx=self.cx * sx,
            cy=self.cy * sy,
            width=int(width),
            height=int(height),
        )

    def downscaled(self, factor: float) -> "Camera":
        """The camera for images downscaled by ``factor`` (as 3DGS ``-r``: round(W / factor))."""
        return self.scaled(downscaled_size(self.width, factor), downscaled_size(self.height, factor))

    def rows(self, y0: int, y1: int) -> "Camera":
        """The camera of image rows ``[y0, y1)``: the same rays, the principal point moved up by
        ``y0`` (row ``y0`` becomes row 0; pixel centres stay at +0.5)."""
        if not 0 <= y0 < y1 <= self.height:
            raise ValueError(f"rows [{y0}, {y1}) are not inside an image of height {self.height}")
        return replace(self, cy=self.cy - y0, height=int(y1 - y0))

    # ----------------------------------------------------------------------------- torch
    def to_torch(self, device=None, dtype=None) -> dict:
        """Tensors for renderers: viewmat [4, 4] world-to-camera and K [3, 3]."""
        import torch

        dtype = dtype or torch.float32
        return {
            "viewmat": torch.as_tensor(self.world_to_camera, dtype=dtype, device=device),
            "K": torch.as_tensor(self.K, dtype=dtype, device=device),
        }


def downscaled_size(size: int, factor: float) -> int:
    """Image side after downscaling by ``factor``, as 3DGS's ``-r`` does it."""
    return max(1, int(round(size / factor)))


def from_opengl_c2w(c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> Camera:
    """Build a Camera from an OpenGL/nerfstudio camera-to-world matrix [3|4, 4]."""
    c2w = np.asarray(c2w, dtype=np.float64)
    if c2w.shape not in ((4, 4), (3, 4)):
        raise ValueError(f"camera-to-world matrix must be 3x4 or 4x4, got shape {c2w.shape}")
    if not np.isfinite(c2w).all():
        raise ValueError("camera-to-world matrix has NaN or infinite entries")
    rot_cv = c2w[:3, :3] @ OPENCV_TO_OPENGL  # camera axes OpenGL -> OpenCV
    center = c2w[:3, 3]
    R = rot_cv.T
    t = -R @ center
    return Camera(fx, fy, cx, cy, width, height, R=R, t=t)


def look_at(
    eye: ArrayLike,  # [3]
    target: ArrayLike,  # [3]
    up: ArrayLike = (0.0, 0.0, 1.0),  # [3]
) -> tuple[np.ndarray, np.ndarray]:  # R [3, 3], t [3]
    """World-to-camera (R, t) for a camera at ``eye`` looking at ``target`` (OpenCV axes; the
    image's "up" is along ``up``)."""
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: view direction is parallel to the up vector")
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    R = np.stack([right, down, forward], axis=0)  # rows: camera axes in world space
    return R, -R @ eye


def qvec_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) -> rotation matrix [3, 3] (COLMAP's convention)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotmat_to_qvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrix [3, 3] -> unit quaternion (w, x, y, z) with w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    K = (
        np.array(
            [
                [R[0, 0] - R[1, 1] - R[2, 2], 0, 0, 0],
                [R[1, 0] + R[0, 1], R[1, 1] - R[0, 0] - R[2, 2], 0, 0],
                [R[2, 0] + R[0, 2], R[2, 1] + R[1, 2], R[2, 2] - R[0, 0] - R[1, 1], 0],
                [R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], R[0, 0] + R[1, 1] + R[2, 2]],
            ]
        )
        / 3.0
    )
    eigvals, eigvecs = np.linalg.eigh(K)
    x, y, z, w = eigvecs[:, np.argmax(eigvals)]
    q = np.array([w, x, y, z])
    return -q if q[0] < 0 else q
