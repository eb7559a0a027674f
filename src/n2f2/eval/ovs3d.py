"""The 3D-OVS segmentation protocol (Liu et al. 2023, "Weakly Supervised 3D Open-vocabulary
Segmentation"), as its reference code (``renderer.evaluation_segmentation_test`` and
``dataLoader/llff.py``) scores it: per-class masks, IoU per class and test view, mean over
classes (and views).

Ground truth layout (3D-OVS release)::

    SCENE/segmentations/classes.txt         one class name a line (the list is sorted)
    SCENE/segmentations/<NN>/<class>.png    mask of <class> in view NN (every class, every view)

* ``NN`` is the camera id: the index of the view in sorted image order (``int(NN)``, no -1,
  unlike LERF-OVS's ``frame_00001``).
* A pixel belongs to a class when its grey value is 255: 3D-OVS reads ``(L / 255).astype(int8)``
  after ``convert("L")``; masks are resized with nearest-neighbour to the evaluated size.
* IoU per (view, class) is sklearn's ``jaccard_score(average=None)``: when a class is absent from
  both the ground truth and the prediction of a view (empty union) its IoU counts as 0
  (``zero_division`` default). ``empty_union="skip"`` leaves such pairs out instead (not 3D-OVS);
  the count is reported either way.
* mIoU is the mean over all (view, class) pairs (3D-OVS's ``np.mean`` over per-view arrays),
  which is also the mean over classes of the per-class mean, as every view has every class.

Predictions. 3D-OVS labels each pixel with its most similar class (``mode="argmax"``; a closed
set, every pixel gets a class), one-hot, and also reports pixel accuracy (sklearn's
``accuracy_score`` on one-hot rows: a pixel is right when its one-hot row equals the ground-truth
row). LangSplat, which reports 3D-OVS in its paper, did not release its 3D-OVS evaluation (its
issues #36, #68), so ``mode="threshold"`` applies LangSplat's LERF-OVS segmentation rule per
class (:func:`n2f2.eval.protocol.segmentation_mask`: box smoothing, threshold 0.4, majority
filter), our reading of "per-class masks" for an open-vocabulary field. With several levels, each
class uses the level whose smoothed map ``R'`` has the highest maximum (LangSplat's rule) in both
modes.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal, Optional, Union

import numpy as np

from ..errors import InputError
from .protocol import (
    LANGSPLAT_MIX,
    ProtocolConfig,
    _as_numpy,
    box_filter,
    mask_from_smoothed,
    resolve_box_size,
    resolve_majority_radius,
)


@dataclass
class Ovs3dView:
    """Ground truth of one test view."""

    name: str  # folder name, e.g. "03"
    view_index: int  # int(name): index in sorted image order
    masks: np.ndarray  # bool [C, H, W], one per class (in Ovs3dLabels.classes order)


@dataclass
class Ovs3dLabels:
    root: Path  # the segmentations folder
    classes: list[str]  # sorted class names
    views: list[Ovs3dView]


def read_ovs3d_segmentations(
    path: Union[str, Path],  # SCENE or SCENE/segmentations
    size: Optional[tuple[int, int]] = None,  # (W, H) to resize masks to (nearest); None = as stored
) -> Ovs3dLabels:
    """Read 3D-OVS ground truth; any problem raises InputError naming the file."""
    from PIL import Image

    from ..data.scene import _DECODE_ERRORS, open_image

    root = Path(path)
    if (root / "segmentations").is_dir():
        root = root / "segmentations"
    classes_file = root / "classes.txt"
    if not classes_file.is_file():
        raise InputError(classes_file, "3D-OVS class list not found (expected segmentations/classes.txt)")
    # Blank lines are not classes (3D-OVS would look for a file named ".png").
    classes = sorted(line.strip() for line in classes_file.read_text().splitlines() if line.strip())
    if not classes:
        raise InputError(classes_file, "class list is empty")
    if len(set(classes)) != len(classes):
        raise InputError(classes_file, "class list has duplicate names")
    folders = sorted((p for p in root.iterdir() if p.is_dir()), key=lambda p: p.name)
    bad = [p.name for p in folders if not p.name.isdigit()]
    if bad:
        raise InputError(root, f"view folders must be named by camera id (digits), got {bad[:3]}")
    if not folders:
        raise InputError(root, "no view folders with ground-truth masks")
    views = []
    for folder in sorted(folders, key=lambda p: int(p.name)):
        masks = []
        for c in classes:
            p = folder / f"{c}.png"
            if not p.is_file():
                raise InputError(p, f"mask of class {c!r} is missing (every view needs every class)")
            with open_image(p) as im:  # a decompression bomb or a non-image: one InputError
                try:
                    im = im.convert("L")
                    if size is not None and im.size != tuple(size):
                        # Pillow puts its filter names into the module at import; Image.Resampling needs Pillow 9.1.
                        im = im.resize(tuple(size), Image.NEAREST)  # pyright: ignore[reportAttributeAccessIssue]
                    masks.append(np.asarray(im) == 255)  # (v / 255).astype(int8) == 1
                except Image.DecompressionBombError as e:
                    raise InputError(p, f"mask is too large to decode safely ({e})") from None
                except _DECODE_ERRORS as e:
                    raise InputError(p, f"cannot read mask ({e})") from None
        shapes = {m.shape for m in masks}
        if len(shapes) != 1:
            raise InputError(folder, f"masks of one view differ in size: {sorted(shapes)}")
        views.append(Ovs3dView(folder.name, int(folder.name), np.stack(masks)))
    return Ovs3dLabels(root, classes, views)


def per_class_iou(
    gt: np.ndarray,  # bool [C, H, W]
    pred: np.ndarray,  # bool [C, H, W]
) -> tuple[np.ndarray, np.ndarray]:  # IoU [C] (0 where the union is empty), empty-union flags [C]
    """IoU of each class: |P & G| / |P | G|, 0 on an empty union (sklearn's jaccard_score)."""
    g = np.asarray(gt, dtype=bool).reshape(len(gt), -1)
    p = np.asarray(pred, dtype=bool).reshape(len(pred), -1)
    if g.shape != p.shape:
        raise ValueError(f"ground truth {np.shape(gt)} and prediction {np.shape(pred)} differ")
    inter = (g & p).sum(axis=1)
    union = (g | p).sum(axis=1)
    empty = union == 0
    return np.where(empty, 0.0, inter / np.maximum(union, 1)), empty


def argmax_masks(
    scores: np.ndarray,  # [C, H, W] per-class relevancy / similarity
) -> np.ndarray:  # bool [C, H, W] one-hot of the most relevant class per pixel (first on ties)
    cls = np.argmax(scores, axis=0)
    return np.arange(scores.shape[0])[:, None, None] == cls[None]


@dataclass
class Ovs3dScores:
    classes: list[str]
    mode: str
    per_view: list[dict]  # {"view": name, "view_index": i, "iou": [C], "accuracy": float|None}
    per_class_iou: dict[str, float]  # mean over views
    miou: float  # mean over (view, class) pairs
    accuracy: Optional[float]  # pixel accuracy (argmax mode only)
    empty_unions: int  # (view, class) pairs with empty ground truth and prediction
    box_sizes: list[int] = field(default_factory=list)
    majority_radii: list[int] = field(default_factory=list)
    config: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)


ScoreFn = Callable[[int, list], Any]  # (view index, classes) -> [L, C, H, W] or [C, H, W]


def evaluate_ovs3d(
    score_fn: ScoreFn,  # (view_index, classes) -> relevancy [L, C, H, W] or [C, H, W]
    labels: Ovs3dLabels,
    num_views: int,  # views in the scene (sorted image order)
    mode: Literal["argmax", "threshold"] = "argmax",
    config: ProtocolConfig = ProtocolConfig(),  # box size / threshold for level choice and "threshold"
    empty_union: Literal["zero", "skip"] = "zero",
    progress: bool = True,
) -> Ovs3dScores:
    """Score a scene under the 3D-OVS protocol (see module docstring)."""
    from tqdm import tqdm

    if mode not in ("argmax", "threshold"):
        raise ValueError(f"mode must be 'argmax' or 'threshold', got {mode!r}")
    if empty_union not in ("zero", "skip"):
        raise ValueError(f"empty_union must be 'zero' or 'skip', got {empty_union!r}")
    c = len(labels.classes)
    per_view: list[dict] = []
    all_ious: list[np.ndarray] = []  # [C] per view, NaN where skipped
    accuracies: list[float] = []
    empty_count = 0
    box_sizes: set[int] = set()
    radii: set[int] = set()
    for view in tqdm(labels.views, desc="eval 3D-OVS", unit="view", disable=not progress):
        if not 0 <= view.view_index < num_views:
            raise InputError(labels.root / view.name, f"view {view.view_index} is not in the scene ({num_views} views)")
        rel = np.asarray(_as_numpy(score_fn(view.view_index, list(labels.classes))), dtype=np.float32)
        if rel.ndim == 3:
            rel = rel[None]
        if rel.ndim != 4 or rel.shape[1] != c:
            raise ValueError(f"score_fn must return [L, {c}, H, W], got shape {rel.shape}")
        h, w = rel.shape[-2:]
        if view.masks.shape[1:] != (h, w):
            raise InputError(
                labels.root / view.name,
                f"masks are {view.masks.shape[2]}x{view.masks.shape[1]} but the "
                f"relevancy maps are {w}x{h} (pass size= to read_ovs3d_segmentations)",
            )
        size = resolve_box_size(config.box_size, w, config.box_ref_width)
        radius = resolve_majority_radius(config.majority_radius, w, config.box_ref_width)
        box_sizes.add(size)
        radii.add(radius)
        smoothed = np.float32(LANGSPLAT_MIX) * (box_filter(rel, size) + rel)  # [L, C, H, W]
        level = np.argmax(smoothed.reshape(len(rel), c, -1).max(axis=2), axis=0)  # [C]
        if mode == "argmax":
            pred = argmax_masks(rel[level, np.arange(c)])
            gt_rows = view.masks.reshape(c, -1)
            acc = float((gt_rows == pred.reshape(c, -1)).all(axis=0).mean())
        else:
            pred = np.stack(
                [mask_from_smoothed(smoothed[level[k], k], config.threshold, radius) != 0 for k in range(c)]
            )
            acc = None
        ious, empty = per_class_iou(view.masks, pred)
        empty_count += int(empty.sum())
        if empty_union == "skip":
            ious = np.where(empty, np.nan, ious)
        all_ious.append(ious)
        if acc is not None:
            accuracies.append(acc)
        per_view.append(
            {
                "view": view.name,
                "view_index": view.view_index,
                "iou": [float(v) for v in ious],
                "accuracy": acc,
                "levels": [int(v) for v in level],
            }
        )
    stacked = np.stack(all_ious)  # [V, C]
    if np.isnan(stacked).all():
        raise InputError(labels.root, "every (view, class) pair has an empty ground truth and prediction")
    with np.errstate(invalid="ignore"):
        per_class = {
            name: float(np.nanmean(stacked[:, k])) if not np.isnan(stacked[:, k]).all() else float("nan")
            for k, name in enumerate(labels.classes)
        }
    return Ovs3dScores(
        classes=list(labels.classes),
        mode=mode,
        per_view=per_view,
        per_class_iou=per_class,
        miou=float(np.nanmean(stacked)),
        accuracy=float(np.mean(accuracies)) if accuracies else None,
        empty_unions=empty_count,
        box_sizes=sorted(box_sizes),
        majority_radii=sorted(radii),
        config={**asdict(config), "empty_union": empty_union},
    )
