"""nerfstudio / instant-ngp / Blender ``transforms.json``: read and write.

Reading accepts:

* global intrinsics (``fl_x, fl_y, cx, cy, w, h``) and per-frame overrides of any of them;
* Blender-style ``camera_angle_x`` (and ``camera_angle_y``) instead of focal lengths, with the
  image size then read from the image header, and extension-less ``file_path`` values
  (``./train/r_0`` -> ``./train/r_0.png``);
* lens distortion, returned per frame as a :class:`~n2f2.data.undistort.Lens` (global keys,
  overridden per frame) for :func:`~n2f2.data.load_scene` to undistort:

  - ``camera_model`` ``OPENCV`` (the default), ``PINHOLE``, ``SIMPLE_PINHOLE``,
    ``SIMPLE_RADIAL``, ``RADIAL``: nerfstudio's perspective model, radial ``k1, k2, k3``
    (r^2, r^4, r^6) and tangential ``p1, p2``, which is OpenCV's ``(k1, k2, p1, p2, k3)``.
    nerfstudio's ``k4`` here is an r^8 term OpenCV has no slot for (OpenCV's ``k4`` is a
    denominator term), so a non-zero one is refused; so are ``k5, k6``. instant-ngp files
    (no ``camera_model``) use ``k1, k2, p1, p2`` and read the same way.
  - ``camera_model`` ``OPENCV_FISHEYE``, or instant-ngp's ``"is_fisheye": true``:
    equidistant fisheye ``k1..k4``, OpenCV's ``cv2.fisheye`` model.
  - anything else (``EQUIRECTANGULAR``, ``FISHEYE624``, instant-ngp ``latlong``,
    ``equirectangular``, ``ftheta_p0``) is an :class:`InputError` telling the user to undistort;
* frames whose image file is absent: kept as listed by default; with ``missing="error"`` an
  :class:`InputError` naming how many and which, with ``missing="skip"`` dropped with a
  one-line warning (:func:`~n2f2.data.scene.keep_present_images`; :func:`~n2f2.data.load_scene`
  uses one of these two);
* ``ply_file_path``: sparse points with colours, read with a small PLY reader
  (:func:`read_ply_points`, ascii and binary, ``vertex`` element with ``x y z`` and optional
  ``red green blue``).

``applied_transform`` (written by ``ns-process-data``) records the world change nerfstudio
applied to the COLMAP poses. It is noted but **not** applied: the ``transform_matrix`` values
and the ``ply_file_path`` points are both already expressed in the transformed world, so
they agree with each other as written; applying it would only be needed to line up with the
original COLMAP ``points3D``, which this reader does not mix in.

``transform_matrix`` is an OpenGL camera-to-world matrix; it is converted by
:func:`n2f2.cameras.from_opengl_c2w` (and written by :meth:`Camera.opengl_c2w`) only.
``mask_path`` and ``depth_file_path`` are ignored.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, NamedTuple, Optional, Sequence

import numpy as np

from ..cameras import Camera, from_opengl_c2w
from ..errors import InputError
from ..io import atomic_path, write_json
from .scene import keep_present_images
from .undistort import Lens

TRANSFORMS_NAME = "transforms.json"
_INTRINSIC_KEYS = ("fl_x", "fl_y", "cx", "cy", "w", "h")
_DISTORTION_KEYS = ("k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2")
_PERSPECTIVE_MODELS = {"OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "PERSPECTIVE", "SIMPLE_RADIAL", "RADIAL"}
_FISHEYE_MODELS = {"OPENCV_FISHEYE"}
_UNSUPPORTED_LENS_KEYS = ("latlong", "equirectangular", "ftheta_p0")  # instant-ngp lens modes
UNDISTORT_HINT = (
    "undistort the images first (e.g. process the data with COLMAP's "
    "`colmap image_undistorter`) and write pinhole intrinsics"
)


class TransformsData(NamedTuple):
    """What a ``transforms.json`` describes, at full resolution and in file order."""

    cameras: list[Camera]  # the pinhole part of each frame's camera
    image_paths: list[Path]  # absolute, resolved against the json's folder
    points: Optional[np.ndarray]  # [P, 3] float64 from ply_file_path, or None
    colors: Optional[np.ndarray]  # [P, 3] uint8, or None
    applied_transform: Optional[np.ndarray]  # [3|4, 4] as recorded (not applied)
    lenses: list[Optional[Lens]]  # per frame: its distortion, None for none


def transforms_path(path: str | Path) -> Path:
    """``path`` itself when it names a ``.json`` file, else ``path / "transforms.json"``."""
    path = Path(path)
    return path if path.suffix.lower() == ".json" else path / TRANSFORMS_NAME


# ================================================================================== reading
def read_transforms(path: str | Path, missing: str = "keep") -> TransformsData:
    """Read a ``transforms.json`` (or the one inside folder ``path``); errors name the file.

    Frames whose image is absent are kept (``missing="keep"``), raise one :class:`InputError`
    naming them (``"error"``), or are dropped with a warning line (``"skip"``)."""
    if missing not in ("keep", "error", "skip"):
        raise ValueError(f"missing must be 'keep', 'error' or 'skip', got {missing!r}")
    path = transforms_path(path)
    if not path.is_file():
        raise InputError(path, "file does not exist (a nerfstudio scene needs transforms.json)")
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise InputError(path, f"is not valid JSON ({e.msg} at line {e.lineno}, column {e.colno})") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"cannot read ({e})") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list):
        raise InputError(path, "expected a JSON object with a 'frames' list")
    if not meta["frames"]:
        raise InputError(path, "'frames' is empty: the scene has no images")
    root = path.parent

    frames = list(enumerate(meta["frames"]))
    for index, frame in frames:
        if not isinstance(frame, dict):
            raise InputError(path, f"frame {index} is not a JSON object")
    all_paths = [_frame_image_path(path, root, frame, index) for index, frame in frames]
    keep = (
        range(len(frames))
        if missing == "keep"
        else keep_present_images(all_paths, path, root, skip_missing=missing == "skip")
    )
    cameras, lenses, image_paths = [], [], []
    for k in keep:
        index, frame = frames[k]
        camera, lens = _frame_camera(path, meta, frame, index, all_paths[k])
        cameras.append(camera)
        lenses.append(lens)
        image_paths.append(all_paths[k])

    points = colors = None
    if meta.get("ply_file_path"):
        ply = root / str(meta["ply_file_path"])
        if not ply.is_file():
            raise InputError(ply, f"point cloud listed as ply_file_path in {path.name} does not exist")
        points, colors = read_ply_points(ply)

    applied = None
    if "applied_transform" in meta:
        applied = _matrix(path, meta["applied_transform"], "applied_transform")
    return TransformsData(cameras, image_paths, points, colors, applied, lenses)


def _frame_image_path(path: Path, root: Path, frame: dict, index: int) -> Path:
    file_path = frame.get("file_path")
    if not isinstance(file_path, str) or not file_path:
        raise InputError(path, f"frame {index} has no 'file_path'")
    image_path = root / file_path
    # Blender's nerf_synthetic lists "./train/r_0" for "./train/r_0.png".
    if not image_path.suffix and not image_path.exists() and image_path.with_suffix(".png").exists():
        image_path = image_path.with_suffix(".png")
    return Path(*image_path.parts)  # normalises "./" components


def _matrix(path: Path, value: Any, what: str) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(path, f"{what} is not a matrix of numbers") from None
    if m.shape not in ((4, 4), (3, 4)):
        raise InputError(
            path, f"{what} must be a 4x4 (or 3x4) matrix, got shape {'x'.join(map(str, m.shape)) or 'scalar'}"
        )
    if not np.isfinite(m).all():
        raise InputError(path, f"{what} has NaN or infinite entries")
    return m


def _number(path: Path, value: Any, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(path, f"{what} must be a finite number, got {value!r}")
    return float(value)


def _frame_lens(path: Path, meta: dict, frame: dict, where: str, get) -> Optional[Lens]:
    """The frame's distortion (see the module docstring), or None when it has none."""
    for key in _UNSUPPORTED_LENS_KEYS:
        if key in frame or key in meta:
            raise InputError(path, f"{where}: the instant-ngp {key!r} lens is not supported; {UNDISTORT_HINT}")
    model = frame.get("camera_model", meta.get("camera_model"))
    if model is None:  # instant-ngp marks a fisheye lens with a flag instead
        model = "OPENCV_FISHEYE" if frame.get("is_fisheye", meta.get("is_fisheye", False)) else "OPENCV"
    model = str(model).upper()
    k = {key: get(key) or 0.0 for key in _DISTORTION_KEYS}
    if model in _FISHEYE_MODELS:
        bad = {key: k[key] for key in ("p1", "p2", "k5", "k6") if k[key]}
        if bad:
            raise InputError(path, f"{where}: the {model} model has no {', '.join(bad)} terms, got {bad}")
        return Lens.fisheye(f"transforms.json {model}", k["k1"], k["k2"], k["k3"], k["k4"])
    if model not in _PERSPECTIVE_MODELS:
        raise InputError(path, f"{where}: camera_model {model} is not supported; {UNDISTORT_HINT}")
    bad = {key: k[key] for key in ("k4", "k5", "k6") if k[key]}
    if bad:
        raise InputError(
            path,
            f"{where}: distortion terms {bad} of the {model} model have no OpenCV "
            f"equivalent (nerfstudio's k4 is an r^8 term); {UNDISTORT_HINT}",
        )
    lens = Lens.perspective(f"transforms.json {model}", k1=k["k1"], k2=k["k2"], p1=k["p1"], p2=k["p2"], k3=k["k3"])
    return None if lens.is_pinhole else lens


def _frame_camera(path: Path, meta: dict, frame: dict, index: int, image_path: Path) -> tuple[Camera, Optional[Lens]]:
    where = f"frame {index} ({frame.get('file_path')})"

    def get(key: str) -> Optional[float]:
        value = frame.get(key, meta.get(key))
        return None if value is None else _number(path, value, f"{where}: {key}")

    lens = _frame_lens(path, meta, frame, where, get)

    matrix = frame.get("transform_matrix")
    if matrix is None:
        raise InputError(path, f"{where} has no 'transform_matrix'")
    c2w = _matrix(path, matrix, f"{where}: transform_matrix")

    w, h = get("w"), get("h")
    if w is None or h is None:  # Blender-style files omit the size: read the image header.
        w, h = _image_size(image_path, path)
    fx, fy = get("fl_x"), get("fl_y")
    if fx is None:
        angle_x = _angle(path, get("camera_angle_x"), f"{where}: camera_angle_x")
        if angle_x is None:
            raise InputError(path, f"{where}: no focal length (fl_x) and no camera_angle_x")
        fx = 0.5 * w / math.tan(0.5 * angle_x)
    if fy is None:
        angle_y = _angle(path, get("camera_angle_y"), f"{where}: camera_angle_y")
        fy = 0.5 * h / math.tan(0.5 * angle_y) if angle_y is not None else fx
    cx, cy = get("cx"), get("cy")
    cx = w / 2.0 if cx is None else cx
    cy = h / 2.0 if cy is None else cy
    if w != int(w) or h != int(h):
        raise InputError(path, f"{where}: image size must be whole pixels, got w={w}, h={h}")
    try:
        return from_opengl_c2w(c2w, fx, fy, cx, cy, int(w), int(h)), lens
    except ValueError as e:
        raise InputError(path, f"{where}: {e}") from None


def _angle(path: Path, value: Optional[float], what: str) -> Optional[float]:
    """A field of view in radians, strictly between 0 and pi (or None when absent)."""
    if value is not None and not 0.0 < value < math.pi:
        raise InputError(path, f"{what} must be a field of view in radians between 0 and pi, got {value}")
    return value


def _image_size(image_path: Path, source: Path) -> tuple[int, int]:
    from .scene import open_image

    if not image_path.is_file():
        raise InputError(image_path, f"image listed in {source.name} does not exist")
    with open_image(image_path) as im:  # reads the header only
        return im.size


# ================================================================================== writing
def write_transforms(
    path: str | Path,
    cameras: Sequence[Camera],
    image_relpaths: Sequence[str],  # relative to the json's folder
    points: Optional[np.ndarray] = None,  # [P, 3] -> sparse_pc.ply, optional
    colors: Optional[np.ndarray] = None,  # [P, 3] uint8
) -> None:
    """Write a nerfstudio ``transforms.json`` (``path`` is the file, or a folder to put it in).

    Intrinsics are written once at the top level when all cameras share them, else per frame.
    ``camera_model`` is ``OPENCV`` with zero distortion (what ``ns-process-data`` writes for an
    undistorted capture). ``transform_matrix`` is :meth:`Camera.opengl_c2w`. With ``points``,
    a binary PLY ``sparse_pc.ply`` is written beside it and referenced as ``ply_file_path``.
    """
    path = transforms_path(path)
    if len(cameras) != len(image_relpaths):
        raise ValueError(f"need one image path per camera, got {len(cameras)} cameras and {len(image_relpaths)} paths")
    if not cameras:
        raise ValueError("need at least one camera")

    def intrinsics(c: Camera) -> dict:
        return {"fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": c.width, "h": c.height}

    shared = all(intrinsics(c) == intrinsics(cameras[0]) for c in cameras)
    meta: dict[str, Any] = {"camera_model": "OPENCV"}
    if shared:
        meta.update(intrinsics(cameras[0]))
    meta.update({k: 0.0 for k in ("k1", "k2", "p1", "p2")})
    frames = []
    for cam, rel in zip(cameras, image_relpaths):
        frame: dict[str, Any] = {"file_path": str(rel)}
        if not shared:
            frame.update(intrinsics(cam))
        frame["transform_matrix"] = cam.opengl_c2w().tolist()
        frames.append(frame)
    meta["frames"] = frames
    if points is not None:
        write_ply_points(path.parent / "sparse_pc.ply", points, colors)
        meta["ply_file_path"] = "sparse_pc.ply"
    write_json(path, meta)


# ================================================================================== PLY
# PLY scalar type names (both spellings) -> numpy dtype character.
PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


def read_ply_points(path: str | Path) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """``points [P, 3] float64`` and ``colors [P, 3] uint8`` (or ``None`` without ``red green
    blue``) from the ``vertex`` element of an ascii or binary PLY file. The vertex element must
    come first and have no list properties (true of every point-cloud PLY in practice)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise InputError(path, f"cannot read ({e.strerror or e})") from None
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise InputError(path, "not a PLY file (no 'ply' magic or no 'end_header')")
    body_start = data.find(b"\n", end) + 1
    header = data[:end].decode("ascii", errors="replace").splitlines()
    fmt, element, count, props = None, None, 0, []
    for line in header:
        words = line.split()
        if not words:
            continue
        if words[0] == "format":
            fmt = words[1] if len(words) > 1 else None
        elif words[0] == "element":
            if element == "vertex":
                break  # vertex properties are complete
            if len(words) < 3:
                raise InputError(path, f"malformed header line {line!r}")
            if words[1] != "vertex":
                raise InputError(path, f"the first element is {words[1]!r}; expected 'vertex'")
            if not words[2].isdigit():
                raise InputError(path, f"vertex count {words[2]!r} is not a whole number >= 0")
            element, count = "vertex", int(words[2])
        elif words[0] == "property" and element == "vertex":
            if len(words) < 3:
                raise InputError(path, f"malformed header line {line!r}")
            if words[1] == "list":
                raise InputError(path, "vertex element has a list property; not a point cloud")
            if words[1] not in PLY_TYPES or len(words) < 3:
                raise InputError(path, f"unsupported property {line!r}")
            props.append((words[2], PLY_TYPES[words[1]]))
    names = [n for n, _ in props]
    if element != "vertex" or not {"x", "y", "z"} <= set(names):
        raise InputError(path, "needs a 'vertex' element with x, y, z properties")

    if fmt == "ascii":
        if 2 * count * len(props) - 1 > len(data) - body_start:  # each value but the last takes 2 bytes or more
            raise InputError(
                path,
                f"file is truncated: header says {count} vertices with {len(props)} values "
                f"each, the file holds {len(data) - body_start} bytes after the header",
            )
        rows = data[body_start:].decode("ascii", errors="replace").split("\n")
        rows = [r for r in rows if r.strip()][:count]
        try:
            table = np.array(" ".join(rows).split(), dtype=np.float64)
        except ValueError:
            raise InputError(path, "vertex data contains something that is not a number") from None
        if table.size != count * len(props):
            raise InputError(
                path,
                f"file is truncated: expected {count} vertices with {len(props)} "
                f"values each, found {table.size} values",
            )
        columns: dict[str, np.ndarray] = {n: table.reshape(count, len(props))[:, k] for k, n in enumerate(names)}
    elif fmt in ("binary_little_endian", "binary_big_endian"):
        order = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(n, order + t) for n, t in props])
        need = dtype.itemsize * count
        if len(data) - body_start < need:
            raise InputError(
                path,
                f"file is truncated: expected {need} bytes of vertex data at offset "
                f"{body_start}, but only {len(data) - body_start} remain",
            )
        table = np.frombuffer(data, dtype=dtype, count=count, offset=body_start)
        columns = {n: table[n] for n in names}
    else:
        raise InputError(path, f"unsupported PLY format {fmt!r}")

    points = np.stack([columns["x"], columns["y"], columns["z"]], axis=1).astype(np.float64)
    if not np.isfinite(points).all():
        raise InputError(path, "point coordinates have NaN or infinite entries")
    colors = None
    if {"red", "green", "blue"} <= set(names):
        rgb = np.stack([columns["red"], columns["green"], columns["blue"]], axis=1)
        if dict(props)["red"].startswith("f"):
            rgb = rgb * 255.0  # float colours are in [0, 1]
        colors = np.clip(np.round(rgb.astype(np.float64)), 0, 255).astype(np.uint8)
    return points, colors


def write_ply_points(
    path: str | Path,
    points: np.ndarray,  # [P, 3]
    colors: Optional[np.ndarray] = None,  # [P, 3] uint8
) -> None:
    """Binary little-endian PLY with ``double x y z`` and (optionally) ``uchar red green blue``."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if colors is not None:
        colors = np.asarray(colors)
        if colors.shape != points.shape or colors.dtype != np.uint8:
            raise ValueError(f"colors must be uint8 {points.shape}, got {colors.dtype} {colors.shape}")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    table = np.zeros(len(points), dtype=np.dtype(fields))
    for k, axis in enumerate("xyz"):
        table[axis] = points[:, k]
    if colors is not None:
        for k, channel in enumerate(("red", "green", "blue")):
            table[channel] = colors[:, k]
    kind = {"<f8": "double", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(points)}"]
    header += [f"property {kind[t]} {n}" for n, t in fields] + ["end_header"]
    with atomic_path(path) as tmp:
        tmp.write_bytes(("\n".join(header) + "\n").encode("ascii") + table.tobytes())
