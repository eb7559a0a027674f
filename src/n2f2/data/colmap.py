"""COLMAP sparse models (``sparse/0``): read and write, binary and text.

Camera models: ``SIMPLE_PINHOLE`` and ``PINHOLE`` load as they are. The distortion models
OpenCV can undistort (``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``, ``FULL_OPENCV``,
``OPENCV_FISHEYE``, ``SIMPLE_RADIAL_FISHEYE``, ``RADIAL_FISHEYE``) are read as their pinhole
part plus a :class:`~n2f2.data.undistort.Lens`, which :func:`~n2f2.data.load_scene` uses to
undistort the images (see :mod:`n2f2.data.undistort`). ``FOV`` with ``omega = 0`` is a
pinhole; the other models (``FOV``, ``THIN_PRISM_FISHEYE``, ``RAD_TAN_THIN_PRISM_FISHEYE``)
are refused with an error telling the user to run ``colmap image_undistorter``. Parameter
orders are COLMAP's (``src/colmap/sensor/models.h``), and so is the pixel convention, which
is n2f2's (top-left pixel centre at 0.5, 0.5).

COLMAP stores, per image, the world-to-camera rotation as a quaternion ``qvec`` (w, x, y, z)
and the translation ``tvec`` with OpenCV camera axes, which is exactly n2f2's
:class:`~n2f2.cameras.Camera` convention; the quaternion is converted with
:func:`~n2f2.cameras.qvec_to_rotmat` / :func:`~n2f2.cameras.rotmat_to_qvec`.

File formats (little-endian, packed), as COLMAP's ``read_write_model.py`` writes them:

* ``cameras.bin``: ``u64 count``, then per camera ``i32 id, i32 model_id, u64 width,
  u64 height, f64 params[n(model)]``.
* ``images.bin``: ``u64 count``, then per image ``i32 id, f64 qvec[4], f64 tvec[3],
  i32 camera_id, name (NUL-terminated), u64 n_points2D, (f64 x, f64 y, i64 point3D_id) * n``.
* ``points3D.bin``: ``u64 count``, then per point ``u64 id, f64 xyz[3], u8 rgb[3],
  f64 error, u64 track_length, (i32 image_id, i32 point2D_idx) * track_length``.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple, Optional, Sequence

import numpy as np

from ..cameras import Camera, qvec_to_rotmat, rotmat_to_qvec
from ..errors import InputError
from ..io import write_bytes, write_text
from .undistort import Lens

# COLMAP camera models: id -> (name, number of params). From colmap/src/colmap/sensor/models.h.
CAMERA_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
CAMERA_MODEL_IDS = {name: (model_id, n) for model_id, (name, n) in CAMERA_MODELS.items()}

# Models n2f2 reads: (index of fx, index of fy or None for a single focal, a function from
# the distortion parameters, those after fx [fy] cx cy, to a Lens, or None for a pinhole).
# Fisheye models map to a fisheye Lens even with zero parameters: they are still
# equidistant, not pinhole, projections.
_MODELS = {
    "SIMPLE_PINHOLE": (0, None, None),
    "PINHOLE": (0, 1, None),
    "SIMPLE_RADIAL": (0, None, lambda k: Lens.perspective("COLMAP SIMPLE_RADIAL", k1=k[0])),
    "RADIAL": (0, None, lambda k: Lens.perspective("COLMAP RADIAL", k1=k[0], k2=k[1])),
    "OPENCV": (0, 1, lambda k: Lens.perspective("COLMAP OPENCV", k1=k[0], k2=k[1], p1=k[2], p2=k[3])),
    "FULL_OPENCV": (
        0,
        1,
        lambda k: Lens.perspective(
            "COLMAP FULL_OPENCV", k1=k[0], k2=k[1], p1=k[2], p2=k[3], k3=k[4], k4=k[5], k5=k[6], k6=k[7]
        ),
    ),
    "OPENCV_FISHEYE": (0, 1, lambda k: Lens.fisheye("COLMAP OPENCV_FISHEYE", *k)),
    "SIMPLE_RADIAL_FISHEYE": (0, None, lambda k: Lens.fisheye("COLMAP SIMPLE_RADIAL_FISHEYE", k1=k[0])),
    "RADIAL_FISHEYE": (0, None, lambda k: Lens.fisheye("COLMAP RADIAL_FISHEYE", k1=k[0], k2=k[1])),
    "FOV": (0, 1, "omega"),  # a pinhole when omega = 0, refused otherwise
}

UNDISTORT_HINT = (
    "undistort the images first, e.g. `colmap image_undistorter --image_path images "
    "--input_path sparse/0 --output_path undistorted --output_type COLMAP`, "
    "then use the undistorted folder"
)


@dataclass(frozen=True)
class ColmapCamera:
    """One entry of ``cameras.bin|txt``."""

    id: int
    model: str
    width: int
    height: int
    params: tuple[float, ...]


@dataclass(frozen=True)
class ColmapImage:
    """One entry of ``images.bin|txt`` (2D keypoints are skipped: n2f2 does not use them)."""

    id: int
    qvec: tuple[float, float, float, float]  # world-to-camera rotation (w, x, y, z)
    tvec: tuple[float, float, float]  # world-to-camera translation
    camera_id: int
    name: str  # relative to the images folder


# ================================================================================== reading
def find_model_files(sparse_dir: str | Path) -> Optional[tuple[str, dict[str, Path]]]:
    """``("binary"|"text", {"cameras": path, "images": path, "points3D": path})`` for the
    model in ``sparse_dir``, binary preferred (as COLMAP and 3DGS do), or ``None``.

    ``points3D`` may be absent (the path is then returned anyway and reads as no points)."""
    sparse_dir = Path(sparse_dir)
    for kind, ext in (("binary", ".bin"), ("text", ".txt")):
        files = {name: sparse_dir / f"{name}{ext}" for name in ("cameras", "images", "points3D")}
        if files["cameras"].is_file() and files["images"].is_file():
            return kind, files
    return None


def read_colmap_model(
    sparse_dir: str | Path,
) -> tuple[dict[int, ColmapCamera], list[ColmapImage], Optional[np.ndarray], Optional[np.ndarray]]:
    """Read a COLMAP model folder (binary preferred over text).

    Returns ``(cameras, images, points, colors)``: cameras by id, images in file order,
    ``points [P, 3] float64`` and ``colors [P, 3] uint8``, or ``None, None`` when there is no
    ``points3D`` file or it holds no point.
    """
    sparse_dir = Path(sparse_dir)
    found = find_model_files(sparse_dir)
    if found is None:
        raise InputError(
            sparse_dir,
            "no COLMAP model here: expected cameras.bin + images.bin "
            "(+ points3D.bin) or cameras.txt + images.txt (+ points3D.txt)",
        )
    kind, files = found
    if kind == "binary":
        cameras = read_cameras_binary(files["cameras"])
        images = read_images_binary(files["images"])
        points, colors = read_points3d_binary(files["points3D"]) if files["points3D"].is_file() else (None, None)
    else:
        cameras = read_cameras_text(files["cameras"])
        images = read_images_text(files["images"])
        points, colors = read_points3d_text(files["points3D"]) if files["points3D"].is_file() else (None, None)
    if points is not None and len(points) == 0:
        points, colors = None, None
    for image in images:
        if image.camera_id not in cameras:
            raise InputError(
                files["images"],
                f"image {image.name!r} uses camera id {image.camera_id}, which {files['cameras'].name} does not define",
            )
    return cameras, images, points, colors


class ColmapScene(NamedTuple):
    """A COLMAP model as n2f2 cameras, in ``images`` file order."""

    cameras: list[Camera]
    image_names: list[str]  # relative to the images folder
    points: Optional[np.ndarray]  # [P, 3] float64, or None
    colors: Optional[np.ndarray]  # [P, 3] uint8, or None
    kind: str  # "binary" or "text"
    files: dict[str, Path]  # "cameras", "images", "points3D"
    lenses: list[Optional[Lens]]  # per image: its camera's distortion, None for a pinhole


def read_colmap_scene(sparse_dir: str | Path) -> ColmapScene:
    """Read a model folder and convert it to n2f2 cameras (the pinhole part of each camera
    model) and lenses (its distortion). Errors name the file at fault: an unsupported camera
    model names ``cameras.*``, a bad pose names ``images.*``."""
    sparse_dir = Path(sparse_dir)
    raw_cameras, images, points, colors = read_colmap_model(sparse_dir)
    found = find_model_files(sparse_dir)
    assert found is not None  # read_colmap_model raised InputError when there is no model
    kind, files = found
    if not images:
        raise InputError(files["images"], "lists no images")
    lenses = {
        cam_id: colmap_lens(cam, files["cameras"])
        for cam_id, cam in raw_cameras.items()
        if any(im.camera_id == cam_id for im in images)
    }
    cameras = [
        colmap_to_camera(raw_cameras[im.camera_id], im, files["images"], lenses[im.camera_id][0]) for im in images
    ]
    return ColmapScene(
        cameras, [im.name for im in images], points, colors, kind, files, [lenses[im.camera_id][1] for im in images]
    )


def colmap_lens(camera: ColmapCamera, source: Path) -> tuple[tuple[float, float, float, float], Optional[Lens]]:
    """``((fx, fy, cx, cy), lens)`` of a COLMAP camera: its pinhole part and its distortion
    (``None`` for a pinhole model). A model n2f2 cannot undistort raises an
    :class:`InputError` naming ``source`` and telling the user to undistort first."""
    model, p = camera.model, camera.params
    if model not in _MODELS:
        raise InputError(
            source, f"camera {camera.id} uses the {model} model, which n2f2 cannot undistort; {UNDISTORT_HINT}"
        )
    if not all(math.isfinite(v) for v in p):
        raise InputError(source, f"camera {camera.id} has NaN or infinite parameters {list(p)}")
    ifx, ify, make_lens = _MODELS[model]
    fx = p[ifx]
    fy = p[ify] if ify is not None else fx
    cx, cy = (p[1], p[2]) if ify is None else (p[2], p[3])
    extra = p[3:] if ify is None else p[4:]
    if fx <= 0 or fy <= 0:
        raise InputError(source, f"camera {camera.id} has focal length fx={fx}, fy={fy}; both must be positive")
    _check_size(source, f"camera {camera.id}", camera.width, camera.height)
    if make_lens == "omega":
        if any(extra):
            raise InputError(
                source,
                f"camera {camera.id} uses the {model} model with omega = {extra[0]}, "
                f"which n2f2 cannot undistort; {UNDISTORT_HINT}",
            )
        make_lens = None
    lens = make_lens(extra) if make_lens is not None else None
    return (fx, fy, cx, cy), lens


def colmap_to_camera(
    camera: ColmapCamera,
    image: ColmapImage,
    source: Path,
    intrinsics: Optional[tuple[float, float, float, float]] = None,
) -> Camera:
    """Build an n2f2 :class:`Camera` from a COLMAP camera and image (``source`` names the file
    in error messages; ``intrinsics`` defaults to the pinhole part from :func:`colmap_lens`,
    without the distortion, which the caller must handle)."""
    fx, fy, cx, cy = intrinsics if intrinsics is not None else colmap_lens(camera, source)[0]
    q = np.asarray(image.qvec, dtype=np.float64)
    t = np.asarray(image.tvec, dtype=np.float64)
    if not (np.isfinite(q).all() and np.isfinite(t).all()):
        raise InputError(
            source,
            f"image {image.name!r} has a NaN or infinite pose (qvec={list(image.qvec)}, tvec={list(image.tvec)})",
        )
    if np.linalg.norm(q) < 1e-12:
        raise InputError(source, f"image {image.name!r} has a zero quaternion")
    try:
        return Camera(fx, fy, cx, cy, camera.width, camera.height, R=qvec_to_rotmat(q), t=t)
    except ValueError as e:
        raise InputError(source, f"image {image.name!r} (camera {camera.id}): {e}") from None


class _BinaryReader:
    """Sequential little-endian reader that turns a short read into an :class:`InputError`
    naming the file, the offset and the bytes it needed."""

    def __init__(self, path: Path):
        self.path = path
        try:
            self.data = path.read_bytes()
        except OSError as e:
            raise InputError(path, f"cannot read ({e.strerror or e})") from None
        self.offset = 0

    def _need(self, n: int, what: str) -> None:
        if self.offset + n > len(self.data):
            raise InputError(
                self.path,
                f"file is truncated: expected {n} bytes ({what}) at offset "
                f"{self.offset}, but the file has {len(self.data)} bytes",
            )

    def unpack(self, fmt: str, what: str) -> tuple:
        size = struct.calcsize(fmt)
        self._need(size, what)
        values = struct.unpack_from(fmt, self.data, self.offset)
        self.offset += size
        return values

    def skip(self, n: int, what: str) -> None:
        self._need(n, what)
        self.offset += n

    def cstring(self, what: str) -> str:
        end = self.data.find(b"\x00", self.offset)
        if end < 0:
            raise InputError(
                self.path,
                f"file is truncated: {what} at offset {self.offset} has no "
                f"terminating NUL byte before the end of the file",
            )
        raw = self.data[self.offset : end]
        self.offset = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError:
            raise InputError(self.path, f"{what} at offset {self.offset} is not valid UTF-8") from None

    def count(self, what: str) -> int:
        (n,) = self.unpack("<Q", what)
        return n


def read_cameras_binary(path: str | Path) -> dict[int, ColmapCamera]:
    r = _BinaryReader(Path(path))
    cameras = {}
    for k in range(r.count("camera count")):
        cam_id, model_id, width, height = r.unpack("<iiQQ", f"camera #{k} header")
        if model_id not in CAMERA_MODELS:
            raise InputError(
                r.path, f"camera {cam_id} has unknown model id {model_id} (is this really a COLMAP cameras.bin?)"
            )
        model, n_params = CAMERA_MODELS[model_id]
        params = r.unpack(f"<{n_params}d", f"{n_params} parameters of camera {cam_id} ({model})")
        _check_size(r.path, f"camera {cam_id}", width, height)
        cameras[cam_id] = ColmapCamera(cam_id, model, int(width), int(height), tuple(params))
    return cameras


def read_images_binary(path: str | Path) -> list[ColmapImage]:
    r = _BinaryReader(Path(path))
    images = []
    for k in range(r.count("image count")):
        image_id, qw, qx, qy, qz, tx, ty, tz, cam_id = r.unpack("<idddddddi", f"image #{k} pose")
        name = r.cstring(f"name of image {image_id}")
        n2d = r.count(f"2D point count of image {name!r}")
        r.skip(24 * n2d, f"{n2d} 2D points of image {name!r}")
        images.append(ColmapImage(image_id, (qw, qx, qy, qz), (tx, ty, tz), cam_id, name))
    return images


# Bytes of one points3D.bin record without its track: id, xyz, rgb, error, track length.
_POINT_RECORD_BYTES = struct.calcsize("<QdddBBBdQ")


def read_points3d_binary(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """``points [P, 3] float64``, ``colors [P, 3] uint8``. Tracks are skipped."""
    r = _BinaryReader(Path(path))
    n = r.count("point count")
    room = len(r.data) - r.offset
    if n * _POINT_RECORD_BYTES > room:
        raise InputError(
            r.path,
            f"file is truncated: it declares {n} points, expected at least "
            f"{_POINT_RECORD_BYTES} bytes each, but only {room} bytes remain",
        )
    points = np.empty((n, 3), dtype=np.float64)
    colors = np.empty((n, 3), dtype=np.uint8)
    head = struct.Struct("<QdddBBBdQ")  # id, xyz, rgb, error, track length
    for k in range(n):
        _, x, y, z, cr, cg, cb, _, track = r.unpack(head.format, f"point #{k}")
        r.skip(8 * track, f"track of point #{k}")
        points[k] = (x, y, z)
        colors[k] = (cr, cg, cb)
    _check_points_finite(r.path, points, lambda k: f"point #{k}")
    return points, colors


def _check_points_finite(
    path: Path,
    points: np.ndarray,  # [P, 3]
    where,
) -> None:
    """An :class:`InputError` naming the first point (``where(k)``) with a NaN or infinite coordinate."""
    bad = np.flatnonzero(~np.isfinite(points).all(axis=1))
    if bad.size:
        more = f" ({bad.size} points are)" if bad.size > 1 else ""
        raise InputError(path, f"{where(int(bad[0]))} has a NaN or infinite coordinate{more}")


def _check_size(path: Path, what: str, width, height) -> None:
    if not (0 < width < 2**31 and 0 < height < 2**31):
        raise InputError(path, f"{what} has image size {width}x{height}; width and height must be positive")


def _text_lines(path: Path):
    """Yield ``(line_number, stripped_line)`` for every line, comments included as ``""``."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as e:
        raise InputError(path, f"cannot read ({e.strerror or e})") from None
    except UnicodeDecodeError:
        raise InputError(path, "is not a UTF-8 text file (a binary COLMAP file named .txt?)") from None
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.strip()
        yield number, "" if line.startswith("#") else line


def read_cameras_text(path: str | Path) -> dict[int, ColmapCamera]:
    path = Path(path)
    cameras = {}
    for number, line in _text_lines(path):
        if not line:
            continue
        elems = line.split()
        try:
            cam_id, model, width, height = int(elems[0]), elems[1], int(elems[2]), int(elems[3])
            params = tuple(float(v) for v in elems[4:])
        except (ValueError, IndexError):
            raise InputError(
                path, f"line {number}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...', got {line[:80]!r}"
            ) from None
        if model not in CAMERA_MODEL_IDS:
            raise InputError(path, f"line {number}: unknown camera model {model!r}")
        if len(params) != CAMERA_MODEL_IDS[model][1]:
            raise InputError(
                path, f"line {number}: the {model} model has {CAMERA_MODEL_IDS[model][1]} parameters, got {len(params)}"
            )
        _check_size(path, f"line {number}: camera {cam_id}", width, height)
        cameras[cam_id] = ColmapCamera(cam_id, model, width, height, params)
    return cameras


def read_images_text(path: str | Path) -> list[ColmapImage]:
    """Each image takes two lines: the pose line and its 2D-point line (which may be empty),
    as COLMAP writes them; comment lines are skipped."""
    path = Path(path)
    images = []
    lines = iter(_text_lines(path))
    for number, line in lines:
        if not line:
            continue
        elems = line.split()
        try:
            image_id = int(elems[0])
            qvec = tuple(float(v) for v in elems[1:5])
            tvec = tuple(float(v) for v in elems[5:8])
            cam_id = int(elems[8])
            name = " ".join(elems[9:])
            if len(qvec) != 4 or len(tvec) != 3 or not name:
                raise ValueError
        except (ValueError, IndexError):
            raise InputError(
                path, f"line {number}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', got {line[:80]!r}"
            ) from None
        images.append(ColmapImage(image_id, qvec, tvec, cam_id, name))
        next(lines, None)  # the 2D-point line of this image
    return images


def read_points3d_text(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    path = Path(path)
    xyz, rgb, numbers = [], [], []
    for number, line in _text_lines(path):
        if not line:
            continue
        elems = line.split(maxsplit=8)
        try:
            xyz.append((float(elems[1]), float(elems[2]), float(elems[3])))
            rgb.append((int(elems[4]), int(elems[5]), int(elems[6])))
        except (ValueError, IndexError):
            raise InputError(
                path, f"line {number}: expected 'POINT3D_ID X Y Z R G B ERROR TRACK...', got {line[:80]!r}"
            ) from None
        numbers.append(number)
    points = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    _check_points_finite(path, points, lambda k: f"line {numbers[k]}")
    colors = np.asarray(rgb, dtype=np.int64).reshape(-1, 3)
    if colors.size and (colors.min() < 0 or colors.max() > 255):
        raise InputError(path, "point colours must be in 0..255")
    return points, colors.astype(np.uint8)


# ================================================================================== writing
def _model_from_cameras(
    cameras: Sequence[Camera], image_names: Sequence[str]
) -> tuple[list[ColmapCamera], list[ColmapImage]]:
    """COLMAP cameras (PINHOLE, one per distinct intrinsics, ids from 1) and images (ids from 1)."""
    if len(cameras) != len(image_names):
        raise ValueError(f"need one image name per camera, got {len(cameras)} cameras and {len(image_names)} names")
    intrinsics_ids: dict[tuple, int] = {}
    colmap_cameras: list[ColmapCamera] = []
    colmap_images: list[ColmapImage] = []
    for i, (cam, name) in enumerate(zip(cameras, image_names)):
        key = (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
        if key not in intrinsics_ids:
            intrinsics_ids[key] = len(intrinsics_ids) + 1
            colmap_cameras.append(
                ColmapCamera(intrinsics_ids[key], "PINHOLE", cam.width, cam.height, (cam.fx, cam.fy, cam.cx, cam.cy))
            )
        q = rotmat_to_qvec(cam.R)
        colmap_images.append(
            ColmapImage(
                i + 1,
                (float(q[0]), float(q[1]), float(q[2]), float(q[3])),  # q [4] wxyz
                (float(cam.t[0]), float(cam.t[1]), float(cam.t[2])),  # t [3]
                intrinsics_ids[key],
                str(name),
            )
        )
    return colmap_cameras, colmap_images


def _check_points(points: Optional[np.ndarray], colors: Optional[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    if points is None:
        return np.zeros((0, 3), np.float64), np.zeros((0, 3), np.uint8)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if colors is None:
        colors = np.full(points.shape, 128, dtype=np.uint8)
    colors = np.asarray(colors)
    if colors.shape != points.shape:
        raise ValueError(f"colors must be [P, 3] like points {points.shape}, got {colors.shape}")
    if colors.dtype != np.uint8:
        raise ValueError(f"colors must be uint8, got {colors.dtype}")
    return points, colors


def write_colmap_text(
    sparse_dir: str | Path,
    cameras: Sequence[Camera],
    image_names: Sequence[str],  # relative to the images folder
    points: Optional[np.ndarray] = None,  # [P, 3] world space
    colors: Optional[np.ndarray] = None,  # [P, 3] uint8 (default grey)
) -> None:
    """Write ``cameras.txt``, ``images.txt`` and ``points3D.txt`` (PINHOLE cameras, empty 2D
    point lists and tracks) into ``sparse_dir``. Floats are written with ``repr`` so that
    reading them back is exact."""
    sparse_dir = Path(sparse_dir)
    colmap_cameras, colmap_images = _model_from_cameras(cameras, image_names)
    points, colors = _check_points(points, colors)

    lines = [
        "# Camera list with one line of data per camera:",
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
        f"# Number of cameras: {len(colmap_cameras)}",
    ]
    lines += [
        f"{c.id} {c.model} {c.width} {c.height} " + " ".join(repr(float(v)) for v in c.params) for c in colmap_cameras
    ]
    write_text(sparse_dir / "cameras.txt", "\n".join(lines) + "\n")

    lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
        f"# Number of images: {len(colmap_images)}, mean observations per image: 0",
    ]
    for im in colmap_images:
        lines.append(f"{im.id} " + " ".join(repr(v) for v in (*im.qvec, *im.tvec)) + f" {im.camera_id} {im.name}")
        lines.append("")
    write_text(sparse_dir / "images.txt", "\n".join(lines) + "\n")

    lines = [
        "# 3D point list with one line of data per point:",
        "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
        f"# Number of points: {len(points)}, mean track length: 0",
    ]
    lines += [
        f"{k + 1} {p[0]!r} {p[1]!r} {p[2]!r} {c[0]} {c[1]} {c[2]} 0.0"
        for k, (p, c) in enumerate(zip(points.tolist(), colors.tolist()))
    ]
    write_text(sparse_dir / "points3D.txt", "\n".join(lines) + "\n")


def write_colmap_binary(
    sparse_dir: str | Path,
    cameras: Sequence[Camera],
    image_names: Sequence[str],  # relative to the images folder
    points: Optional[np.ndarray] = None,  # [P, 3] world space
    colors: Optional[np.ndarray] = None,  # [P, 3] uint8 (default grey)
) -> None:
    """Write ``cameras.bin``, ``images.bin`` and ``points3D.bin`` into ``sparse_dir`` (same
    content as :func:`write_colmap_text`)."""
    sparse_dir = Path(sparse_dir)
    colmap_cameras, colmap_images = _model_from_cameras(cameras, image_names)
    points, colors = _check_points(points, colors)

    out = [struct.pack("<Q", len(colmap_cameras))]
    for c in colmap_cameras:
        model_id, n_params = CAMERA_MODEL_IDS[c.model]
        out.append(struct.pack(f"<iiQQ{n_params}d", c.id, model_id, c.width, c.height, *c.params))
    write_bytes(sparse_dir / "cameras.bin", b"".join(out))

    out = [struct.pack("<Q", len(colmap_images))]
    for im in colmap_images:
        out.append(struct.pack("<idddddddi", im.id, *im.qvec, *im.tvec, im.camera_id))
        out.append(im.name.encode("utf-8") + b"\x00")
        out.append(struct.pack("<Q", 0))
    write_bytes(sparse_dir / "images.bin", b"".join(out))

    # Points as one packed structured array (no per-point Python loop).
    record = np.dtype([("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("error", "<f8"), ("track", "<u8")])
    table = np.zeros(len(points), dtype=record)
    table["id"] = np.arange(1, len(points) + 1)
    table["xyz"] = points
    table["rgb"] = colors
    write_bytes(sparse_dir / "points3D.bin", struct.pack("<Q", len(points)) + table.tobytes())
