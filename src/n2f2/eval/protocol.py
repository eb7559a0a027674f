"""LangSplat's evaluation protocol on the expanded LERF-OVS labels, detail for detail.

The reference is LangSplat's ``eval/evaluate_iou_loc.py`` (with ``eval/utils.py`` and
``eval/openclip_encoder.py``). Every rule it applies is reproduced here and written down next to
the code that applies it; where this module differs (bad input, an optional box size), the
difference is opt-in or only concerns input LangSplat would crash on or silently mis-score.

Inputs are relevancy maps, not features: the query stage renders features and turns them into
relevancy with the LangSplat formula (:func:`n2f2.field.relevancy.relevancy`, on normalised
features), so the protocol itself never sees a model. Per (frame, category) pair the protocol scores

* **segmentation** (IoU). For each level ``R``: ``R' = 0.5 * (box(R) + R)``; ``R'`` is min-max
  normalised, mapped to [-1, 1], clipped to [0, 1] and thresholded at 0.4; the binary mask goes
  through LangSplat's 7x7 majority filter (:func:`majority_filter`); IoU against the union of the
  category's polygons. The level whose ``R'`` has the highest maximum is the one reported.
* **localization** (hit). For each level ``box(R)`` (no 0.5 mix); the level with the highest
  filtered maximum is chosen; a hit is when any pixel equal to that maximum lies inside any of the
  category's boxes, edges included. The maxima are :func:`n2f2.query.maps.localization_maxima`,
  whose first (:func:`localization_point`) is the point ``n2f2 query`` and the viewer report:
  integer pixel coordinates (x = column, y = row) of the map, the coordinates of the label boxes.

Scene scores: mIoU = mean IoU over all pairs; localization accuracy = hits / pairs.

``box`` is a ``size x size`` mean filter, computed exactly as LangSplat does with
``cv2.filter2D(R, -1, np.ones((size, size)) / size**2)`` on float32 maps: default anchor (the
kernel centre, ``size // 2``, so for the even size 30 the window is rows ``i-15 .. i+14``) and
the default border ``BORDER_REFLECT_101``. LangSplat's size is 30 pixels, chosen for LERF-OVS
images about 986 px wide (LangSplat evaluates at the label resolution: it loads the rendered maps
into arrays of the label's ``(height, width)``). On small renders a 30 px box erases small parts,
so ``box_size="scaled"`` offers ``round(30 * W / 986)`` (W = evaluated width, at least 1). The
majority filter's 7x7 window has the same origin, and ``majority_radius="scaled"`` offers
``round(3 * W / 986)`` (0 keeps the thresholded mask, apart from the far-edge rule).
:meth:`ProtocolConfig.scaled` sets both. The defaults stay LangSplat's exact 30 and 3; the sizes
used are recorded in every result so exact and scaled numbers can both be reported. (On the
160x120 demo scene, 16 views with 8 labelled, 159 pairs, a perfect relevancy map, 1 on the
labelled mask and 0 elsewhere, scores 72.3 mIoU / 94.3 % localization under the exact rules
and 98.3 / 100.0 with both scaled.)

Where this module departs from LangSplat's script, it is on input that script crashes on or
mis-scores without a word, and every departure is counted or raised:

* a label whose frame is not among the scene's views raises (``missing_frames="skip"`` skips it
  and lists it in ``SceneScores.skipped_frames``); LangSplat would index the wrong render or crash;
* two labels for one view raise (LangSplat keeps the last one);
* an object whose polygon covers no pixel of the image is dropped with its box and counted in
  ``skipped_objects``; a category left empty is counted in ``skipped_categories`` (LangSplat
  would score it with an empty ground truth: IoU 0, or NaN);
* relevancy maps of another size than the labels raise (``rescale_labels=True`` scales the
  polygons and boxes instead); images under 2x2 pixels raise (LangSplat's majority filter crashes);
* the frame number comes from the label's ``frame_name`` (``n2f2.data.labels`` takes it from the
  file name; LangSplat from ``info.name``; the two agree in the released LERF-OVS labels).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Literal, Optional, Sequence, Union

import numpy as np

from ..errors import InputError
from ..query.maps import (  # noqa: F401  (re-exported: the protocol's rules, written in query.maps)
    LANGSPLAT_BOX_SIZE,
    LANGSPLAT_MAJORITY_RADIUS,
    LANGSPLAT_MIX,
    LANGSPLAT_THRESHOLD,
    LERF_REFERENCE_WIDTH,
    BoxSize,
    Radius,
    box_filter,
    localization_maxima,
    localization_point,
    majority_filter,
    mask_from_smoothed,
    mask_iou,
    mask_ious,
    max_locations,
    normalized_for_threshold,
    resolve_box_size,
    resolve_majority_radius,
    segmentation_mask,
    smoothed_relevancy,
)

if TYPE_CHECKING:
    from ..data.labels import FrameLabels


@dataclass(frozen=True)
class ProtocolConfig:
    """Settings of the LangSplat protocol. The defaults are LangSplat's exact values."""

    box_size: BoxSize = LANGSPLAT_BOX_SIZE  # int pixels, or "scaled": round(30 * W / ref_width)
    box_ref_width: int = LERF_REFERENCE_WIDTH  # reference width for box_size="scaled"
    threshold: float = LANGSPLAT_THRESHOLD  # segmentation threshold on the [0, 1]-clipped map
    # majority filter half-window (3 -> 7x7), or "scaled": round(3 * W / box_ref_width)
    majority_radius: Radius = LANGSPLAT_MAJORITY_RADIUS
    # A label whose frame is not among the scene's views: "error" (default) raises an InputError;
    # "skip" leaves the frame out and counts it in SceneScores.skipped_frames.
    missing_frames: Literal["error", "skip"] = "error"
    # Labels drawn at another resolution than the relevancy maps: False (LangSplat) raises;
    # True scales polygons and boxes by (W / width, H / height) before rasterising (not LangSplat).
    rescale_labels: bool = False

    def __post_init__(self) -> None:
        if not (self.box_size == "scaled" or (isinstance(self.box_size, int) and self.box_size >= 1)):
            raise ValueError(f"box_size must be a positive int or 'scaled', got {self.box_size!r}")
        if self.box_ref_width < 1:
            raise ValueError(f"box_ref_width must be positive, got {self.box_ref_width}")
        if not 0.0 <= self.threshold < 1.0:
            raise ValueError(f"threshold must be in [0, 1), got {self.threshold}")
        if not (
            self.majority_radius == "scaled" or (isinstance(self.majority_radius, int) and self.majority_radius >= 0)
        ):
            raise ValueError(f"majority_radius must be an int >= 0 or 'scaled', got {self.majority_radius!r}")
        if self.missing_frames not in ("error", "skip"):
            raise ValueError(f"missing_frames must be 'error' or 'skip', got {self.missing_frames!r}")

    @classmethod
    def scaled(cls, ref_width: int = LERF_REFERENCE_WIDTH, **kwargs: Any) -> "ProtocolConfig":
        """LangSplat's rules with both pixel sizes (box, majority window) scaled to the image width."""
        return cls(box_size="scaled", majority_radius="scaled", box_ref_width=ref_width, **kwargs)


def points_in_boxes(
    points: np.ndarray,  # [P, 2] (x, y) pixel indices
    boxes: np.ndarray,  # [B, 4] (x1, y1, x2, y2), either corner order
) -> bool:
    """True when any point lies inside any box, edges included (LangSplat sorts each box's
    corners, then tests ``x_min <= x <= x_max and y_min <= y <= y_max``)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    if len(pts) == 0 or len(b) == 0:
        return False
    x_min = np.minimum(b[:, 0], b[:, 2])
    x_max = np.maximum(b[:, 0], b[:, 2])
    y_min = np.minimum(b[:, 1], b[:, 3])
    y_max = np.maximum(b[:, 1], b[:, 3])
    x, y = pts[:, 0:1], pts[:, 1:2]  # [P, 1] against [B]
    inside = (x >= x_min) & (x <= x_max) & (y >= y_min) & (y <= y_max)
    return bool(inside.any())


def pixels_in_boxes(
    boxes: np.ndarray,  # [B, 4] (x1, y1, x2, y2), either corner order
    height: int,
    width: int,
) -> np.ndarray:  # bool [H, W]
    """The pixels (x = column, y = row) that :func:`points_in_boxes` finds inside any box."""
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    x, y = np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64)
    cols = (x >= np.minimum(b[:, 0], b[:, 2])[:, None]) & (x <= np.maximum(b[:, 0], b[:, 2])[:, None])  # [B, W]
    rows = (y >= np.minimum(b[:, 1], b[:, 3])[:, None]) & (y <= np.maximum(b[:, 1], b[:, 3])[:, None])  # [B, H]
    return np.asarray((rows[:, :, None] & cols[:, None, :]).any(axis=0))


def localization_hit(
    relevancy: np.ndarray,  # [H, W] raw relevancy of one level
    boxes: np.ndarray,  # [B, 4] (x1, y1, x2, y2)
    box_size: int = LANGSPLAT_BOX_SIZE,
) -> bool:
    """LangSplat's localization test for one level: any maximum of ``box(R)``
    (:func:`localization_maxima`) inside any box."""
    return points_in_boxes(localization_maxima(relevancy, box_size), boxes)


# ------------------------------------------------------------------------------ one pair
@dataclass
class PairResult:
    """Scores of one (frame, category) pair."""

    iou: float  # IoU of the chosen segmentation level
    hit: bool  # localization hit on the chosen localization level
    seg_level: int  # level whose R' has the highest maximum (first one on ties)
    loc_level: int  # level whose box(R) has the highest maximum (first one on ties)
    iou_per_level: list[float]  # IoU of every level (the oracle level is max of these)
    hit_per_level: list[bool]  # localization hit of every level's box(R)
    box_size: int  # mean-filter size used, pixels
    majority_radius: int  # majority half-window used, pixels


def evaluate_frame_category(
    relevancy_per_level: np.ndarray,  # [L, H, W] raw relevancy per level (or [H, W] for one)
    gt_mask: np.ndarray,  # [H, W] union mask of the category, non-empty
    boxes: np.ndarray,  # [B, 4] (x1, y1, x2, y2) all boxes of the category
    box_size: int = LANGSPLAT_BOX_SIZE,
    threshold: float = LANGSPLAT_THRESHOLD,
    majority_radius: int = LANGSPLAT_MAJORITY_RADIUS,
) -> PairResult:
    """Segmentation IoU and localization hit of one pair, LangSplat's way (see module doc)."""
    rel = np.asarray(relevancy_per_level, dtype=np.float32)
    if rel.ndim == 2:
        rel = rel[None]
    if rel.ndim != 3 or rel.shape[0] < 1:
        raise ValueError(f"relevancy must be [L, H, W], got shape {np.shape(relevancy_per_level)}")
    gt = np.asarray(gt_mask) != 0
    if gt.shape != rel.shape[1:]:
        raise ValueError(f"ground-truth mask {gt.shape} and relevancy {rel.shape[1:]} differ in size")
    if not gt.any():
        raise ValueError("ground-truth mask is empty")
    if not np.isfinite(rel).all():
        raise ValueError("relevancy contains NaN or infinite values")

    # Segmentation: R' per level; the reported level is the one with the highest max R'.
    filtered = box_filter(rel, box_size)  # [L, H, W]; bitwise the same as per-level filtering
    smoothed = np.float32(LANGSPLAT_MIX) * (filtered + rel)
    ious = mask_ious(mask_from_smoothed(smoothed, threshold, majority_radius), gt)  # [L], level by level
    seg_level = int(np.argmax(smoothed.reshape(len(rel), -1).max(axis=1)))

    # Localization: box(R) without the mix; the level with the highest filtered maximum.
    peaks = filtered.reshape(len(rel), -1).max(axis=1)  # [L]
    loc_level = int(np.argmax(peaks))
    # Any maximum of a level inside any box (localization_hit, i.e. points_in_boxes of
    # localization_maxima, for every level at once): the maxima of each level against the pixels
    # the boxes cover.
    at_peak = filtered == peaks[:, None, None]  # [L, H, W]
    hits = [bool(h) for h in (at_peak & pixels_in_boxes(boxes, *rel.shape[1:])).any(axis=(1, 2))]
    return PairResult(
        iou=float(ious[seg_level]),
        hit=hits[loc_level],
        seg_level=seg_level,
        loc_level=loc_level,
        iou_per_level=[float(v) for v in ious],
        hit_per_level=hits,
        box_size=int(box_size),
        majority_radius=int(majority_radius),
    )


# ------------------------------------------------------------------------------ labels
@dataclass
class CategoryTarget:
    """Ground truth of one category in one frame: union mask and every box."""

    category: str
    mask: np.ndarray  # bool [H, W] union of the category's polygons
    boxes: np.ndarray  # float64 [B, 4] (x1, y1, x2, y2), one per kept object


def frame_targets(
    frame: FrameLabels,
    shape: Optional[tuple[int, int]] = None,  # (H, W) of the relevancy maps; None = label size
    rescale: bool = False,
) -> tuple[list[CategoryTarget], int]:
    """Per-category targets of one label frame, in first-appearance order, and the number of
    objects dropped because their polygon covers no pixel of the image.

    Objects of the same category are unioned and all their boxes kept (LangSplat
    ``stack_mask`` / box concatenation). An object whose filled polygon is empty (entirely
    outside the image) is dropped with its box; a category left with no object is dropped."""
    label_hw = (int(frame.height), int(frame.width))
    if shape is None:
        shape = label_hw
    shape = (int(shape[0]), int(shape[1]))
    scale = (1.0, 1.0)
    if shape != label_hw:
        if not rescale:
            raise ValueError(f"labels are {label_hw[1]}x{label_hw[0]} but the relevancy maps are {shape[1]}x{shape[0]}")
        scale = (shape[1] / label_hw[1], shape[0] / label_hw[0])
    from ..data.labels import polygon_to_mask  # LangSplat's fill: int32 vertices, cv2.fillPoly

    masks: dict[str, np.ndarray] = {}
    boxes: dict[str, list[np.ndarray]] = {}
    dropped = 0
    for obj in frame.objects:
        polygon = np.asarray(obj.polygon, dtype=np.float64).reshape(-1, 2)
        if scale != (1.0, 1.0):
            polygon = polygon * np.asarray(scale)
        # Clipped to the image, like LangSplat. polygon_to_mask reads any [K, 2] array-like through
        # np.asarray; its annotation names only sequences.
        m = polygon_to_mask(polygon, shape[0], shape[1])
        if not m.any():
            dropped += 1
            continue
        box = np.asarray(obj.bbox, dtype=np.float64).reshape(4) * np.array([scale[0], scale[1]] * 2)
        if obj.category in masks:
            masks[obj.category] |= m
            boxes[obj.category].append(box)
        else:
            masks[obj.category] = m
            boxes[obj.category] = [box]
    targets = [CategoryTarget(c, masks[c], np.stack(boxes[c])) for c in masks]
    return targets, dropped


# ------------------------------------------------------------------------------ a scene
@dataclass
class PairRecord:
    """One scored (frame, category) pair."""

    frame: str
    view_index: int
    category: str
    iou: float
    hit: bool
    seg_level: int
    loc_level: int
    iou_per_level: list[float]
    box_size: int
    majority_radius: int = LANGSPLAT_MAJORITY_RADIUS


@dataclass
class SceneScores:
    """Scores of one scene under the LangSplat protocol."""

    pairs: list[PairRecord]
    miou: float  # mean IoU over pairs
    loc_accuracy: float  # hits / pairs
    num_pairs: int
    num_frames: int  # label frames scored
    skipped_frames: list[str] = field(default_factory=list)  # labels of frames not in the scene
    skipped_objects: int = 0  # objects whose polygon covers no pixel of the image
    skipped_categories: int = 0  # (frame, category) pairs left with no object after that
    box_sizes: list[int] = field(default_factory=list)  # distinct filter sizes used
    majority_radii: list[int] = field(default_factory=list)  # distinct majority half-windows used
    config: dict = field(default_factory=dict)

    @property
    def oracle_miou(self) -> float:
        """mIoU with the best level per pair (an upper bound for level selection)."""
        return float(np.mean([max(p.iou_per_level) for p in self.pairs])) if self.pairs else float("nan")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["oracle_miou"] = self.oracle_miou
        return d


RelevancyFn = Callable[[int, list], Any]  # (view index, categories) -> [L, K, H, W] relevancy


def evaluate_scene(
    relevancy_fn: RelevancyFn,  # (view_index, categories) -> [L, K, H, W] (numpy or torch)
    labels: Sequence[Any],  # list[n2f2.data.labels.FrameLabels]
    num_views: int,  # number of views in the scene (sorted image order)
    config: ProtocolConfig = ProtocolConfig(),
    label_dir: Optional[Union[str, Path]] = None,  # named in errors
    progress: bool = True,
) -> SceneScores:
    """Score every (frame, category) pair of a scene's labels.

    ``relevancy_fn(i, categories)`` returns the relevancy maps of view ``i`` for the given
    categories, ``[L, K, H, W]`` with L levels (L = 1 for a single map) and K = len(categories)
    in that order. Frame ``frame_XXXXX`` is view ``XXXXX - 1`` (LangSplat)."""
    from tqdm import tqdm

    from ..data.labels import frame_view_index

    if len(labels) == 0:
        raise InputError(label_dir, "no label frames to evaluate (empty label folder)")
    seen: dict[int, str] = {}
    pairs: list[PairRecord] = []
    skipped_frames: list[str] = []
    skipped_objects = 0
    skipped_categories = 0
    box_sizes: set[int] = set()
    radii: set[int] = set()
    for frame in tqdm(labels, desc="eval", unit="frame", disable=not progress):
        name = str(frame.frame_name)
        try:
            idx = frame_view_index(name)
        except ValueError as e:
            raise InputError(label_dir, str(e)) from None
        if idx in seen:
            raise InputError(label_dir, f"frames {seen[idx]!r} and {name!r} are both view {idx}")
        seen[idx] = name
        if not 0 <= idx < num_views:
            if config.missing_frames == "skip":
                skipped_frames.append(name)
                continue
            raise InputError(
                label_dir,
                f"label {name!r} refers to view {idx}, but the scene has {num_views} views (frame_00001 is view 0)",
            )
        categories = list(dict.fromkeys(o.category for o in frame.objects))
        if not categories:
            continue
        rel = _as_numpy(relevancy_fn(idx, categories))
        if rel.ndim == 3:  # [K, H, W]: a single level
            rel = rel[None]
        if rel.ndim != 4 or rel.shape[1] != len(categories):
            raise ValueError(
                f"relevancy_fn must return [L, {len(categories)}, H, W] for view {idx}, got shape {rel.shape}"
            )
        h, w = rel.shape[-2:]
        try:
            targets, dropped = frame_targets(frame, (h, w), config.rescale_labels)
        except ValueError as e:
            raise InputError(label_dir, f"{name}: {e}") from None
        skipped_objects += dropped
        skipped_categories += len(categories) - len(targets)
        size = resolve_box_size(config.box_size, w, config.box_ref_width)
        radius = resolve_majority_radius(config.majority_radius, w, config.box_ref_width)
        box_sizes.add(size)
        radii.add(radius)
        for t in targets:
            k = categories.index(t.category)
            r = evaluate_frame_category(rel[:, k], t.mask, t.boxes, size, config.threshold, radius)
            pairs.append(
                PairRecord(name, idx, t.category, r.iou, r.hit, r.seg_level, r.loc_level, r.iou_per_level, size, radius)
            )
    if not pairs:
        raise InputError(
            label_dir,
            "no (frame, category) pair left to score "
            f"({len(skipped_frames)} frames skipped, {skipped_objects} "
            "objects outside their image)",
        )
    return SceneScores(
        pairs=pairs,
        miou=float(np.mean([p.iou for p in pairs])),
        loc_accuracy=sum(p.hit for p in pairs) / len(pairs),
        num_pairs=len(pairs),
        num_frames=len({p.frame for p in pairs}),
        skipped_frames=skipped_frames,
        skipped_objects=skipped_objects,
        skipped_categories=skipped_categories,
        box_sizes=sorted(box_sizes),
        majority_radii=sorted(radii),
        config=asdict(config),
    )


def evaluate_label_dir(
    label_dir: Union[str, Path],
    relevancy_fn: RelevancyFn,
    num_views: int,
    config: ProtocolConfig = ProtocolConfig(),
    progress: bool = True,
) -> SceneScores:
    """:func:`evaluate_scene` on the ``frame_XXXXX.json`` files of a folder."""
    from ..data.labels import read_label_dir

    labels = read_label_dir(label_dir)
    return evaluate_scene(relevancy_fn, labels, num_views, config, label_dir, progress)


def _as_numpy(x: Any) -> np.ndarray:
    if isinstance(x, np.ndarray):
        return x
    if hasattr(x, "detach"):  # torch tensor
        return x.detach().float().cpu().numpy()
    return np.asarray(x)
