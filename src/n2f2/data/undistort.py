"""Lens undistortion on load: a view with lens distortion becomes a pinhole view.

Gaussian splatting renders an ideal pinhole camera, so :func:`~n2f2.data.load_scene` turns
every distorted view into a pinhole one before any later stage sees it: it picks a pinhole
camera (:func:`undistorted_camera`) and resamples the image into it with OpenCV
(:func:`undistort_image`). Poses and sparse points are unchanged (they are 3D).

Lens models (:class:`Lens`), in OpenCV's own terms:

* ``"perspective"``: ``cv2`` ``distCoeffs = (k1, k2, p1, p2, k3, k4, k5, k6)``,
  radial ``(1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)`` plus tangential
  ``p1, p2``. COLMAP's ``SIMPLE_RADIAL`` (k), ``RADIAL`` (k1, k2), ``OPENCV`` (k1, k2, p1, p2)
  and ``FULL_OPENCV`` (all eight) are this model; so are nerfstudio's ``OPENCV`` (k1, k2, k3,
  p1, p2) and instant-ngp's default lens (k1, k2, p1, p2).
* ``"fisheye"``: ``cv2.fisheye`` ``(k1, k2, k3, k4)``, the equidistant projection
  ``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``. COLMAP's and
  nerfstudio's ``OPENCV_FISHEYE`` (k1..k4), instant-ngp's ``is_fisheye`` lens, and COLMAP's
  ``SIMPLE_RADIAL_FISHEYE`` (k) and ``RADIAL_FISHEYE`` (k1, k2) are this model. A fisheye
  lens with all-zero coefficients is still equidistant, so it is undistorted too.

Pixel coordinates: COLMAP, nerfstudio and n2f2 put the centre of the top-left pixel at
(0.5, 0.5) (see :mod:`n2f2.cameras`); OpenCV puts it at (0, 0). Intrinsics are shifted by
half a pixel on the way into OpenCV and back (``cx_opencv = cx - 0.5``).

The new pinhole camera (:func:`undistorted_camera`) has the same image size and pose. Its
focal lengths keep the original ``fy / fx`` (pixel aspect) and are scaled by one factor, and
its principal point is placed, so that the whole output image maps inside the distorted
image: every output pixel is a real sample, with no black border. This is what
``cv2.getOptimalNewCameraMatrix(..., alpha=0)`` aims at, computed here from every boundary
pixel instead of a 9x9 grid (which can leave a thin invalid border under strong
distortion), and with square pixels kept square. Barrel distortion therefore crops the
field of view a little, and a fisheye view is cropped to at most 80 degrees off-axis (a
pinhole image cannot reach 90); the output never contains pixels from outside the photo.
A fisheye's centre is also shown at a lower resolution than in the photo, since one pinhole
image of the same size has to span its wide field of view.

Cache: undistorted images are written once, as lossless PNG (same bit depth and channels as
the source, and the source's file stem), to ``<cache>/undistorted/<key>/<stem>.png``, where
``<key>`` hashes the source image path, size and modification time, the camera intrinsics and
the lens. ``<cache>`` is ``cache_dir`` if given, else ``$N2F2_CACHE_DIR``, else
``~/.cache/n2f2``. The user's scene folder is only read. Writes are atomic (temporary file,
then rename), so an interrupted run never leaves a partial image that a later run would
reuse.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import dataclass, replace
from functools import lru_cache
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..cameras import Camera
from ..errors import InputError
from ..io import write_bytes

PERSPECTIVE = "perspective"
FISHEYE = "fisheye"
# Bump when the undistorted pixels or the new camera would change for the same inputs, so
# that older cache entries are not reused.
CACHE_VERSION = 1
CACHE_ENV = "N2F2_CACHE_DIR"
# A pinhole camera cannot show rays at 90 degrees or more from its axis; a fisheye view is
# cropped to at most this half-angle.
MAX_FISHEYE_HALF_ANGLE_DEG = 80.0
# Undistorting more images than this shows a progress bar.
PROGRESS_MIN_IMAGES = 4


@dataclass(frozen=True)
class Lens:
    """A lens distortion model in OpenCV's terms (see the module docstring)."""

    kind: str  # PERSPECTIVE: cv2 (k1, k2, p1, p2, k3, k4, k5, k6); FISHEYE: cv2.fisheye (k1, k2, k3, k4)
    coeffs: tuple[float, ...]
    name: str  # the model as the scene file names it, e.g. "COLMAP SIMPLE_RADIAL"

    @staticmethod
    def perspective(
        name: str,
        k1: float = 0.0,
        k2: float = 0.0,
        p1: float = 0.0,
        p2: float = 0.0,
        k3: float = 0.0,
        k4: float = 0.0,
        k5: float = 0.0,
        k6: float = 0.0,
    ) -> "Lens":
        """OpenCV's rational model; ``k4..k6`` are the denominator terms, as in COLMAP's
        ``FULL_OPENCV`` and ``cv2``."""
        return Lens(PERSPECTIVE, tuple(float(v) for v in (k1, k2, p1, p2, k3, k4, k5, k6)), name)

    @staticmethod
    def fisheye(name: str, k1: float = 0.0, k2: float = 0.0, k3: float = 0.0, k4: float = 0.0) -> "Lens":
        return Lens(FISHEYE, tuple(float(v) for v in (k1, k2, k3, k4)), name)

    @property
    def is_pinhole(self) -> bool:
        """True for a perspective lens without distortion: nothing to undistort."""
        return self.kind == PERSPECTIVE and not any(self.coeffs)


# ============================================================================= geometry
def _intrinsics(camera: Camera) -> tuple[float, float, float, float, int, int]:
    return (camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height)


def _opencv_K(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:  # [3, 3]
    """Camera matrix with OpenCV's pixel-centre convention (top-left pixel centre at 0, 0)."""
    return np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]])


def _undistort_points(
    pixels: np.ndarray,  # [N, 2] distorted, OpenCV pixel coordinates
    intrinsics: tuple,
    lens: Lens,
) -> np.ndarray:  # -> [N, 2] normalised x/z, y/z
    import cv2

    K = _opencv_K(*intrinsics[:4])
    src = np.ascontiguousarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    D = np.asarray(lens.coeffs, dtype=np.float64)
    if lens.kind == FISHEYE:
        out = cv2.fisheye.undistortPoints(src, K, D, criteria=criteria)
    elif hasattr(cv2, "undistortPointsIter"):  # OpenCV 4.x
        # Absent from the stubs of OpenCV versions that lack it; hasattr() above guards the call.
        out = cv2.undistortPointsIter(src, K, D, None, None, criteria)  # pyright: ignore[reportAttributeAccessIssue]
    else:  # OpenCV 5: undistortPoints takes the criteria
        out = cv2.undistortPoints(src, K, D, criteria=criteria)
    return out.reshape(-1, 2)


def _distort_points(
    normalized: np.ndarray,  # [N, 2] x/z, y/z
    intrinsics: tuple,
    lens: Lens,
) -> np.ndarray:  # -> [N, 2] OpenCV pixel coordinates
    import cv2

    K = _opencv_K(*intrinsics[:4])
    D = np.asarray(lens.coeffs, dtype=np.float64)
    pts = np.concatenate([normalized, np.ones((len(normalized), 1))], axis=1).reshape(-1, 1, 3)
    if lens.kind == FISHEYE:
        out, _ = cv2.fisheye.projectPoints(pts, np.zeros(3), np.zeros(3), K, D)
    else:
        out, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), K, D)
    return out.reshape(-1, 2)


@lru_cache(maxsize=64)
def _new_intrinsics(intrinsics: tuple, lens: Lens) -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` of the pinhole camera of :func:`undistorted_camera`, or a
    ``ValueError`` saying why the lens cannot be undistorted."""
    fx, fy, cx, cy, W, H = intrinsics
    # Centres of the outermost pixels, every pixel along each edge (OpenCV coordinates).
    xs, ys = np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64)
    edges = {
        "top": np.stack([xs, np.zeros(W)], 1),
        "bottom": np.stack([xs, np.full(W, H - 1.0)], 1),
        "left": np.stack([np.zeros(H), ys], 1),
        "right": np.stack([np.full(H, W - 1.0), ys], 1),
    }
    limit = math.tan(math.radians(MAX_FISHEYE_HALF_ANGLE_DEG))
    bounds = {"top": -limit, "bottom": limit, "left": -limit, "right": limit}
    for name, pixels in edges.items():
        if lens.kind == FISHEYE:
            # Pixels beyond the largest half-angle kept are cropped anyway (and a lens wider
            # than 180 degrees has no pinhole direction for them): leave them out. In the
            # fisheye model the distorted normalised radius is the distorted angle.
            theta_d = np.hypot((pixels[:, 0] - (cx - 0.5)) / fx, (pixels[:, 1] - (cy - 0.5)) / fy)
            pixels = pixels[theta_d < math.radians(MAX_FISHEYE_HALF_ANGLE_DEG)]
            if not len(pixels):
                continue
        normalized = _undistort_points(pixels, intrinsics, lens)
        # The inverse is iterative: check it by distorting back. It fails where the model is
        # not monotonic (coefficients fitted on a smaller field of view than the image's).
        back = _distort_points(normalized, intrinsics, lens) if np.isfinite(normalized).all() else None
        if back is None or not np.isfinite(back).all() or np.abs(back - pixels).max() > 0.05:
            raise ValueError(
                "its distortion cannot be inverted at the image border (the model folds "
                "over inside the image: are the coefficients right?)"
            )
        # The innermost point of each edge bounds the rectangle every output pixel must map into.
        axis = 1 if name in ("top", "bottom") else 0
        inner = normalized[:, axis].max() if name in ("top", "left") else normalized[:, axis].min()
        bounds[name] = inner if lens.kind != FISHEYE else float(np.clip(inner, -limit, limit))
    left, right, top, bottom = bounds["left"], bounds["right"], bounds["top"], bounds["bottom"]
    if not (right > left and bottom > top):
        raise ValueError("after undistortion no rectangle of valid pixels is left")
    # One zoom factor for both axes (pixel aspect kept): the output's outermost pixel centres
    # land on or inside the valid rectangle, and its centre on the rectangle's centre.
    scale = max(max(W - 1, 1) / ((right - left) * fx), max(H - 1, 1) / ((bottom - top) * fy))
    new_fx, new_fy = scale * fx, scale * fy
    new_cx = (W - 1) / 2.0 - new_fx * (left + right) / 2.0 + 0.5
    new_cy = (H - 1) / 2.0 - new_fy * (top + bottom) / 2.0 + 0.5
    return float(new_fx), float(new_fy), float(new_cx), float(new_cy)


def undistorted_camera(camera: Camera, lens: Lens, source: Optional[Path] = None) -> Camera:
    """The pinhole camera (same size and pose) that a view of ``camera`` with ``lens`` is
    undistorted into; see the module docstring for how it is chosen. ``source`` names the
    scene file in the :class:`InputError` raised when the lens cannot be undistorted."""
    if lens.is_pinhole:
        return camera
    try:
        fx, fy, cx, cy = _new_intrinsics(_intrinsics(camera), lens)
    except ValueError as e:
        raise InputError(
            source, f"cannot undistort the {lens.name} camera with coefficients {list(lens.coeffs)}: {e}"
        ) from None
    return replace(camera, fx=fx, fy=fy, cx=cx, cy=cy)


@lru_cache(maxsize=4)
def _maps(intrinsics: tuple, lens: Lens, new_intrinsics: tuple) -> tuple[np.ndarray, np.ndarray]:
    import cv2

    W, H = intrinsics[4:]
    K, new_K = _opencv_K(*intrinsics[:4]), _opencv_K(*new_intrinsics[:4])
    D = np.asarray(lens.coeffs, dtype=np.float64)
    if lens.kind == FISHEYE:
        map_x, map_y = cv2.fisheye.initUndistortRectifyMap(K, D, np.eye(3), new_K, (W, H), cv2.CV_32FC1)
    else:
        map_x, map_y = cv2.initUndistortRectifyMap(K, D, None, new_K, (W, H), cv2.CV_32FC1)
    map_x.setflags(write=False)
    map_y.setflags(write=False)
    return map_x, map_y


def undistortion_maps(camera: Camera, lens: Lens, new_camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """``map_x, map_y`` float32 [H, W] for ``cv2.remap``: for each pixel of ``new_camera``'s
    image, where it is in the distorted image of ``camera`` (OpenCV pixel coordinates, i.e.
    n2f2 coordinates minus 0.5). Both cameras must have the same size."""
    if (camera.width, camera.height) != (new_camera.width, new_camera.height):
        raise ValueError("undistortion maps need the two cameras at the same image size")
    return _maps(_intrinsics(camera), lens, _intrinsics(new_camera))


def undistort_image(
    image: np.ndarray,  # [h, w] or [h, w, C] any dtype cv2.remap takes
    camera: Camera,
    lens: Lens,
    new_camera: Camera,
) -> np.ndarray:  # -> same shape
    """Resample a distorted image of ``camera`` into ``new_camera`` (bilinear). The image may
    be a resized copy of the camera's (same aspect ratio): both cameras are scaled to it."""
    import cv2

    h, w = image.shape[:2]
    if (w, h) != (camera.width, camera.height):
        camera, new_camera = camera.scaled(w, h), new_camera.scaled(w, h)
    map_x, map_y = undistortion_maps(camera, lens, new_camera)
    # Output pixels map inside the photo by construction; replicating the edge only absorbs
    # rounding at the outermost pixel centres.
    return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


# ============================================================================= cache
def cache_root(cache_dir: Optional[str | Path] = None) -> Path:
    """``cache_dir``, else ``$N2F2_CACHE_DIR``, else ``~/.cache/n2f2``."""
    if cache_dir is None:
        cache_dir = os.environ.get(CACHE_ENV) or Path.home() / ".cache" / "n2f2"
    return Path(cache_dir).expanduser()


def cache_key(image_path: Path, camera: Camera, lens: Lens) -> str:
    """Hash of everything the undistorted image depends on (the pose is not: it does not
    change pixels). Raises :class:`InputError` when the image cannot be stat'ed."""
    try:
        st = image_path.stat()
    except OSError as e:
        raise InputError(image_path, f"cannot read image ({e.strerror or e})") from None
    inputs = {
        "version": CACHE_VERSION,
        "source": str(image_path.resolve()),
        "bytes": st.st_size,
        "mtime_ns": st.st_mtime_ns,
        "intrinsics": [repr(float(v)) for v in _intrinsics(camera)],
        "lens": [lens.kind, *map(repr, lens.coeffs)],
    }
    return hashlib.sha256(json.dumps(inputs, sort_keys=True).encode("utf-8")).hexdigest()[:24]


def _read_image(path: Path) -> np.ndarray:
    """Decoded pixels exactly as stored (bit depth, channels, no EXIF rotation: the same
    orientation the rest of n2f2 reads)."""
    import cv2

    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as e:
        raise InputError(path, f"cannot read image ({e.strerror or e})") from None
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if image is None:
        raise InputError(path, "cannot read image (not an image format OpenCV can decode)")
    if image.dtype not in (np.uint8, np.uint16):
        raise InputError(path, f"cannot undistort {image.dtype} images; expected 8- or 16-bit")
    return image


def _undistort_file(source: Path, target: Path, camera: Camera, lens: Lens, new_camera: Camera) -> None:
    import cv2

    image = _read_image(source)
    out = undistort_image(image, camera, lens, new_camera)
    ok, png = cv2.imencode(".png", out)
    if not ok:
        raise InputError(source, "could not encode the undistorted image as PNG")
    try:
        write_bytes(target, png.tobytes())
    except OSError as e:
        raise InputError(
            target.parent,
            f"cannot write the undistorted image cache ({e.strerror or e}); set {CACHE_ENV} to a writable folder",
        ) from None


def undistort_views(
    cameras: Sequence[Camera],
    lenses: Sequence[Optional[Lens]],
    image_paths: Sequence[Path],
    cache_dir: Optional[str | Path] = None,
    listing: Optional[Path] = None,
) -> tuple[list[Camera], list[Path]]:
    """Pinhole cameras and image paths for every view: a view without distortion (lens
    ``None`` or pinhole) is returned as it is; a distorted one gets its
    :func:`undistorted_camera` and its cached undistorted PNG, written now if the cache does
    not hold it yet. ``listing`` names the scene file in errors."""
    from concurrent.futures import ThreadPoolExecutor

    from tqdm import tqdm

    root = cache_root(cache_dir) / "undistorted"
    out_cameras, out_paths, todo = [], [], []
    for camera, lens, path in zip(cameras, lenses, image_paths):
        if lens is None or lens.is_pinhole:
            out_cameras.append(camera)
            out_paths.append(path)
            continue
        new_camera = undistorted_camera(camera, lens, listing)
        target = root / cache_key(path, camera, lens) / f"{path.stem}.png"
        if not target.is_file():
            todo.append((path, target, camera, lens, new_camera))
        out_cameras.append(new_camera)
        out_paths.append(target)
    if todo:
        # OpenCV releases the GIL while decoding, remapping and encoding.
        with (
            ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as pool,
            tqdm(
                total=len(todo), desc="undistorting images", unit="image", disable=len(todo) <= PROGRESS_MIN_IMAGES
            ) as bar,
        ):
            futures = [pool.submit(_undistort_file, *job) for job in todo]
            try:
                for future in futures:
                    future.result()
                    bar.update(1)
            except BaseException:
                for future in futures:
                    future.cancel()
                raise
        _maps.cache_clear()  # full-size float maps: do not keep them past the load
    return out_cameras, out_paths
