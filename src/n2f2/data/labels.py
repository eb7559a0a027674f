"""Evaluation labels in LangSplat's expanded-LERF format, and the mask <-> polygon conversion.

One JSON file per labelled view, ``label/frame_XXXXX.json``::

    {"info": {"name": "frame_00001.jpg", "height": H, "width": W},
     "objects": [{"category": "red mug", "bbox": [x1, y1, x2, y2],
                  "segmentation": [[x, y], ...]}, ...]}

Conventions (as LangSplat's ``evaluate_iou_loc.py`` reads them):

* Frame number ``k`` in ``frame_XXXXX`` is view index ``k - 1`` (the k-th image in sorted
  file-name order). The index is taken from the JSON file's name.
* Polygon vertices ``[x, y]`` are pixel *indices* (column, row), the coordinates OpenCV's
  ``findContours`` / ``fillPoly`` use: the pixel centre of column ``x`` is at the continuous
  coordinate ``u = x + 0.5`` of :mod:`n2f2.cameras`. A polygon becomes a mask with
  ``cv2.fillPoly`` on ``int32`` vertices (truncated, like LangSplat), boundary included.
  A polygon reaching more than one image size outside the image is first clipped to that
  box (exact polygon clipping: its area inside the image is unchanged; OpenCV may round the
  clipped edges' boundary pixels differently), so huge coordinates neither overflow ``int32``
  nor make the fill walk empty space.
* A category may occur several times in one frame (several connected pieces, or several
  instances); its mask is the union of its polygons.
* ``bbox`` is ``[x1, y1, x2, y2]``, the inclusive pixel-index bounds of the polygon.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np

from ..errors import InputError
from ..io import write_json

_FRAME_RE = re.compile(r"^frame_(\d+)$")
# Largest label image (height x width): twice PIL's decompression-bomb warning limit, the most
# pixels n2f2 decodes from an image file.
MAX_LABEL_PIXELS = 2 * 89_478_485


@dataclass
class LabelObject:
    """One labelled polygon: a query string and one connected piece of its mask."""

    category: str
    bbox: tuple[float, float, float, float]  # x1, y1, x2, y2 (inclusive pixel indices)
    polygon: list[list[float]]  # [[x, y], ...] pixel indices (column, row)


@dataclass
class FrameLabels:
    """The labels of one view."""

    frame_name: str  # "frame_00001" (file stem; view index = number - 1)
    height: int
    width: int
    objects: list[LabelObject] = field(default_factory=list)

    @property
    def view_index(self) -> int:
        return frame_view_index(self.frame_name)

    @property
    def categories(self) -> list[str]:
        """Distinct categories, in first-occurrence order."""
        return list(dict.fromkeys(o.category for o in self.objects))

    def mask(self, category: str) -> np.ndarray:
        """bool [H, W]: union of the category's polygons (all False if it is not labelled)."""
        out = np.zeros((self.height, self.width), dtype=bool)
        for obj in self.objects:
            if obj.category == category:
                out |= polygon_to_mask(obj.polygon, self.height, self.width)
        return out

    def bboxes(self, category: str) -> np.ndarray:
        """float64 [K, 4] boxes (x1, y1, x2, y2) of the category's pieces."""
        boxes = [o.bbox for o in self.objects if o.category == category]
        return np.asarray(boxes, dtype=np.float64).reshape(-1, 4)


def frame_name(view_index: int) -> str:
    """View index 0 -> ``frame_00001`` (LangSplat numbering)."""
    if view_index < 0:
        raise ValueError(f"view index must be >= 0, got {view_index}")
    return f"frame_{view_index + 1:05d}"


def frame_view_index(name: str) -> int:
    """``frame_00001`` (or ``frame_00001.jpg``) -> view index 0."""
    m = _FRAME_RE.match(Path(name).stem)
    if m is None or int(m.group(1)) < 1:
        raise ValueError(f"not a LangSplat frame name (frame_XXXXX, numbered from 1): {name!r}")
    return int(m.group(1)) - 1


# ----------------------------------------------------------------------------- masks <-> polygons
def polygon_to_mask(
    polygon: np.ndarray | Sequence[Sequence[float]],  # [K, 2] (x, y) pixel indices
    height: int,
    width: int,
) -> np.ndarray:
    """bool [H, W]: the polygon filled with ``cv2.fillPoly`` (int32 vertices, as LangSplat).
    A polygon reaching beyond one image size outside the image is clipped to that box first
    (see the module docstring)."""
    import cv2

    pts = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    margin = max(height, width)
    box = (-margin, -margin, width - 1 + margin, height - 1 + margin)  # x0, y0, x1, y1
    if len(pts) and ((pts[:, 0] < box[0]) | (pts[:, 0] > box[2]) | (pts[:, 1] < box[1]) | (pts[:, 1] > box[3])).any():
        pts = clip_polygon(pts, box)
    mask = np.zeros((height, width), dtype=np.uint8)
    if len(pts):
        cv2.fillPoly(mask, [pts.astype(np.int32)], 1)
    return mask.astype(bool)


def clip_polygon(
    points: np.ndarray,  # [K, 2] (x, y)
    box: tuple[float, float, float, float],  # x0, y0, x1, y1
) -> np.ndarray:  # [M, 2] float64
    """Sutherland-Hodgman: the polygon cut by each side of ``box`` in turn. Every point inside
    the box keeps its winding number (a part cut off by one side cannot wind around a point on
    the other side), so even-odd and non-zero filling inside the box are unchanged."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    x0, y0, x1, y1 = box
    # (axis, bound, sign): keep the points where sign * (p[axis] - bound) <= 0
    for axis, bound, sign in ((0, x0, -1.0), (0, x1, 1.0), (1, y0, -1.0), (1, y1, 1.0)):
        if len(pts) == 0:
            break
        nxt = np.roll(pts, -1, axis=0)
        d_cur = sign * (pts[:, axis] - bound)
        d_nxt = sign * (nxt[:, axis] - bound)
        out = []
        for p, q, dp, dq in zip(pts, nxt, d_cur, d_nxt):
            if dp <= 0:
                out.append(p)
            if (dp <= 0) != (dq <= 0):  # the edge crosses the side: add the crossing
                c = p + (dp / (dp - dq)) * (q - p)
                c[axis] = bound
                out.append(c)
        pts = np.asarray(out, dtype=np.float64).reshape(-1, 2)
    return pts


def mask_to_polygons(
    mask: np.ndarray,  # [H, W] bool
    min_area: int = 4,
) -> list[np.ndarray]:
    """One polygon (int32 [K, 2], (x, y) pixel indices) per connected piece of ``mask``.

    LangSplat's format has no holes, so each hole (e.g. the gap inside a mug handle, or a
    plate under the fruit) is spliced into its outer contour through a zero-width cut: the
    result, filled with ``cv2.fillPoly`` (even-odd), reproduces the hole. Pieces with fewer
    than ``min_area`` pixels are dropped (specks from occlusion boundaries).
    """
    import cv2

    m = np.ascontiguousarray(mask.astype(np.uint8))
    if not m.any():
        return []
    contours, hierarchy = cv2.findContours(m, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    hierarchy = hierarchy.reshape(-1, 4)  # next, previous, first child, parent
    polygons = []
    for i, contour in enumerate(contours):
        if hierarchy[i, 3] != -1:  # a hole; handled with its outer contour
            continue
        outer = contour.reshape(-1, 2)
        if _piece_area(outer, m.shape) < min_area:
            continue
        poly = outer
        child = hierarchy[i, 2]
        while child != -1:
            hole = contours[child].reshape(-1, 2)
            if len(hole) >= 3:
                poly = _splice_hole(poly, hole)
            child = hierarchy[child, 0]
        polygons.append(poly.astype(np.int32))
    return polygons


def _piece_area(outer: np.ndarray, shape: tuple[int, int]) -> int:
    """Pixels covered by the filled outer contour (including its boundary pixels)."""
    import cv2

    canvas = np.zeros(shape, dtype=np.uint8)
    cv2.fillPoly(canvas, [outer.astype(np.int32)], 1)
    return int(canvas.sum())


def _splice_hole(poly: np.ndarray, hole: np.ndarray) -> np.ndarray:
    """Join ``hole`` into ``poly`` through the closest pair of vertices (a cut traversed
    there and back, which even-odd filling ignores)."""
    d2 = ((poly[:, None, :].astype(np.int64) - hole[None, :, :]) ** 2).sum(-1)
    i, j = np.unravel_index(int(np.argmin(d2)), d2.shape)
    hole_loop = np.concatenate([hole[j:], hole[: j + 1]], axis=0)
    return np.concatenate([poly[: i + 1], hole_loop, poly[i:]], axis=0)


def polygon_bbox(polygon: np.ndarray) -> tuple[float, float, float, float]:  # polygon [K, 2]
    p = np.asarray(polygon, dtype=np.float64).reshape(-1, 2)
    return (float(p[:, 0].min()), float(p[:, 1].min()), float(p[:, 0].max()), float(p[:, 1].max()))


def labels_from_masks(
    frame: str,
    masks: Mapping[str, np.ndarray],  # category -> bool [H, W]
    min_area: int = 4,
) -> FrameLabels:
    """Frame labels with one object per connected piece of each category's mask."""
    shapes = {m.shape for m in masks.values()}
    if len(shapes) > 1:
        raise ValueError(f"masks of one frame must share a shape, got {sorted(shapes)}")
    height, width = shapes.pop() if shapes else (0, 0)
    objects = []
    for category, mask in masks.items():
        for poly in mask_to_polygons(mask, min_area=min_area):
            objects.append(LabelObject(category, polygon_bbox(poly), poly.tolist()))
    return FrameLabels(frame, int(height), int(width), objects)


# ----------------------------------------------------------------------------- files
def write_frame_labels(path: str | Path, labels: FrameLabels) -> None:
    """Write one ``frame_XXXXX.json`` (atomically). ``info.name`` is ``<frame>.jpg`` as in
    LangSplat's label folders, whose evaluation script parses the frame number from it."""

    def num(x: float) -> float | int:
        return int(x) if float(x).is_integer() else float(x)

    obj = {
        "info": {"name": f"{labels.frame_name}.jpg", "height": int(labels.height), "width": int(labels.width)},
        "objects": [
            {
                "category": o.category,
                "bbox": [num(v) for v in o.bbox],
                "segmentation": [[num(x), num(y)] for x, y in o.polygon],
            }
            for o in labels.objects
        ],
    }
    write_json(path, obj)


def read_frame_labels(path: str | Path) -> FrameLabels:
    """Read and validate one label file; any problem raises InputError naming the file."""
    path = Path(path)
    try:
        frame = Path(path).stem
        frame_view_index(frame)
    except ValueError:
        raise InputError(path, "label file name must be frame_XXXXX.json (numbered from 1)") from None
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"cannot read label file ({e})") from None
    except json.JSONDecodeError as e:
        raise InputError(path, f"not valid JSON ({e.msg} at line {e.lineno})") from None
    if not isinstance(data, dict):
        raise InputError(path, "label file must hold a JSON object with 'info' and 'objects'")
    info = data.get("info")
    if not isinstance(info, dict):
        raise InputError(path, "missing or invalid 'info' object")
    for key in ("height", "width"):
        if not _is_int(info.get(key)) or info[key] <= 0:
            raise InputError(path, f"'info.{key}' must be a positive integer, got {info.get(key)!r}")
    if info["height"] * info["width"] > MAX_LABEL_PIXELS:
        raise InputError(
            path,
            f"'info' declares a {info['width']}x{info['height']} image, more than the "
            f"{MAX_LABEL_PIXELS} pixels a label mask may have",
        )
    if "name" in info and not isinstance(info["name"], str):
        raise InputError(path, f"'info.name' must be a string, got {info['name']!r}")
    objs = data.get("objects")
    if not isinstance(objs, list):
        raise InputError(path, "missing or invalid 'objects' list")
    objects = []
    for k, o in enumerate(objs):
        where = f"objects[{k}]"
        if not isinstance(o, dict):
            raise InputError(path, f"{where} must be an object")
        for key in ("category", "bbox", "segmentation"):
            if key not in o:
                raise InputError(path, f"{where} has no '{key}'")
        if not isinstance(o["category"], str) or not o["category"].strip():
            raise InputError(path, f"{where}.category must be a non-empty string")
        bbox = o["bbox"]
        if not isinstance(bbox, list) or len(bbox) != 4 or not all(_is_num(v) for v in bbox):
            raise InputError(path, f"{where}.bbox must be [x1, y1, x2, y2] numbers, got {bbox!r}")
        seg = o["segmentation"]
        if (
            not isinstance(seg, list)
            or not seg
            or not all(isinstance(p, list) and len(p) == 2 and all(_is_num(v) for v in p) for p in seg)
        ):
            raise InputError(path, f"{where}.segmentation must be a non-empty list of [x, y] numbers")
        objects.append(
            LabelObject(
                o["category"],
                (float(bbox[0]), float(bbox[1]), float(bbox[2]), float(bbox[3])),  # checked above: 4 numbers
                [[float(x), float(y)] for x, y in seg],
            )
        )
    return FrameLabels(frame, int(info["height"]), int(info["width"]), objects)


def read_label_dir(directory: str | Path) -> list[FrameLabels]:
    """All ``frame_*.json`` of a label folder, sorted by view index."""
    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(directory, "label folder does not exist")
    files = sorted(directory.glob("frame_*.json"))
    if not files:
        raise InputError(directory, "label folder has no frame_XXXXX.json files")
    frames = [read_frame_labels(f) for f in files]
    return sorted(frames, key=lambda f: f.view_index)


def write_label_dir(directory: str | Path, frames: Iterable[FrameLabels]) -> list[Path]:
    paths = []
    for f in frames:
        p = Path(directory) / f"{f.frame_name}.json"
        write_frame_labels(p, f)
        paths.append(p)
    return paths


def _is_int(v: object) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v: object) -> bool:
    if not isinstance(v, (int, float)) or isinstance(v, bool):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:  # an integer too large for a float
        return False
