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

A trained run is scored by :func:`evaluate_run_ovs3d` (``n2f2 eval RUN --labels SCENE`` picks it
when ``SCENE`` or ``SCENE/segmentations`` holds a ``classes.txt``): each listed view is rendered
once; composite gives one map per class, and so does soft (:mod:`n2f2.query.soft`, made from the
scales' maps); explicit / levels hand every scale to the rule above
(the scale whose ``R'`` peaks highest, per class and box size; only the chosen map is kept), under
LangSplat's exact 30 px box and the box scaled to the image width, as the 2D runner reports both.
Oracle mode is left out: the argmax prediction couples the classes, so a best scale per class is
not a bound. :func:`export_ovs3d` (``n2f2 export-ovs3d``) writes a generated scene in this layout:
the class masks are the scene's exact region maps at one level.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Literal, Optional, Union

import numpy as np

from ..errors import InputError
from ..query.modes import ORACLE, QUERY_MODES
from .protocol import (
    LANGSPLAT_MIX,
    ProtocolConfig,
    _as_numpy,
    box_filter,
    mask_from_smoothed,
    resolve_box_size,
    resolve_majority_radius,
)

if TYPE_CHECKING:
    from ..query.engine import QueryEngine


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


# ------------------------------------------------------------------------------ layout
OVS3D_FORMAT = "n2f2-eval-ovs3d-v1"  # eval.json of a 3D-OVS evaluation
GROUND_TRUTH_NAMES = ("regions", "regions.json", "depth", "label", "queries.json", "segmentations")


def ovs3d_labels_path(path: Union[str, Path]) -> Optional[Path]:
    """The ``segmentations`` folder when ``path`` (a scene or its ``segmentations``) is in the
    3D-OVS layout, else None."""
    p = Path(path)
    if (p / "classes.txt").is_file():
        return p
    if (p / "segmentations" / "classes.txt").is_file():
        return p / "segmentations"
    return None


def _class_file_name(name: str, where: Path) -> str:
    """``name`` as a mask file stem (3D-OVS names masks ``<class>.png``); refuses names that are
    not a plain file name."""
    if not name or name != name.strip() or name in (".", "..") or any(c in name for c in "/\\\0\n"):
        raise InputError(where, f"region name {name!r} cannot be a 3D-OVS class (mask file) name")
    return name


def export_ovs3d(
    scene_dir: Union[str, Path],  # a generated scene (regions/*.npy + regions.json)
    out: Union[str, Path],
    *,
    level: str = "object",  # the regions.json level whose regions become the classes
    views: Optional[list[int]] = None,  # views with masks; default: scene.json's labelled views, else all
    force: bool = False,
) -> dict:
    """Write a generated scene in the 3D-OVS layout: ``OUT`` holds a copy of the scene's images and
    cameras (every file but the ground truth: region maps, depth, labels, queries) and
    ``OUT/segmentations/`` with ``classes.txt`` (the names of the regions at ``level``, sorted) and
    ``<NN>/<class>.png`` (255 where the region map at that level holds the class's region id, 0
    elsewhere; every class in every listed view). Returns ``{"classes", "views", "level"}``."""
    from ..data import load_scene
    from ..data.scene import read_scene_meta
    from ..io import claim_out_dir, remove_results, write_bytes, write_png, write_text

    scene_dir, out = Path(scene_dir), Path(out)
    if not (scene_dir / "regions.json").is_file():
        raise InputError(scene_dir, "not a generated scene with region maps (no regions.json)")
    if out.resolve() == scene_dir.resolve() or scene_dir.resolve() in out.resolve().parents:
        raise InputError(out, "the 3D-OVS copy must be written outside the scene folder")
    scene = load_scene(scene_dir)
    gt = scene.ground_truth
    if gt is None:
        raise InputError(scene_dir, "not a generated scene with region maps (no regions.json)")
    regions = gt.regions
    level_names = list(regions.get("levels", ["part", "object", "group"]))
    if level not in level_names:
        raise InputError(scene_dir / "regions.json", f"level {level!r} is not one of {', '.join(level_names)}")
    li = level_names.index(level)
    chosen = [r for r in regions["regions"] if int(r["level"]) == li]
    names = [_class_file_name(str(r["name"]), scene_dir / "regions.json") for r in chosen]
    if not chosen:
        raise InputError(scene_dir / "regions.json", f"no region at level {level!r}")
    if len(set(names)) != len(names):
        raise InputError(scene_dir / "regions.json", f"two regions at level {level!r} share a name")
    n = len(scene.cameras)
    if views is None:
        views = [int(v) for v in read_scene_meta(scene_dir).get("labelled_views") or range(n)]
    bad = [v for v in views if not 0 <= int(v) < n]
    if bad:
        raise InputError(scene_dir, f"views {bad} are not in the scene ({n} views)")
    views = sorted(dict.fromkeys(int(v) for v in views))
    copies = sorted(p for p in scene_dir.iterdir() if p.name not in GROUND_TRUTH_NAMES and not p.name.startswith("."))
    present = claim_out_dir(out, [p.name for p in copies] + ["segmentations"], force=force, resume_flag=None)
    remove_results(out, present)
    for src in copies:
        for f in [src] if src.is_file() else sorted(q for q in src.rglob("*") if q.is_file()):
            write_bytes(out / f.relative_to(scene_dir), f.read_bytes())
    seg = out / "segmentations"
    order = sorted(range(len(chosen)), key=lambda k: names[k])
    for v in views:
        ids = np.asarray(gt.region_ids(v))[li]  # [H, W]
        for k in order:
            mask = np.where(ids == int(chosen[k]["id"]), 255, 0).astype(np.uint8)
            write_png(seg / f"{v:02d}" / f"{names[k]}.png", mask)
    write_text(seg / "classes.txt", "".join(names[k] + "\n" for k in order))
    return {"classes": [names[k] for k in order], "views": views, "level": level}


# ------------------------------------------------------------------------------ a trained run
def evaluate_run_ovs3d(
    engine: QueryEngine,  # the run's
    labels_path: Union[str, Path],  # SCENE or SCENE/segmentations in the 3D-OVS layout
    *,
    modes: Optional[list[str]] = None,  # default: every mode the field supports but oracle
    prediction: Literal["argmax", "threshold"] = "argmax",
    empty_union: Literal["zero", "skip"] = "zero",
    progress: bool = True,
    on_ready: Optional[Callable[[], None]] = None,  # called once the inputs are checked
) -> dict:
    """Score a trained run under the 3D-OVS protocol (see the module docstring). Returns the
    ``eval.json`` dict (format ``n2f2-eval-ovs3d-v1``)."""
    import time

    from tqdm import tqdm

    from ..query.soft import soft_relevancy
    from .protocol import resolve_box_size, smoothed_relevancy

    t_start = time.perf_counter()
    if engine.scene is None:
        raise InputError(engine.run_dir, "the run does not record its scene folder: pass --scene DIR")
    supported = list(engine.modes())
    wanted = list(dict.fromkeys(modes or supported))
    for m in wanted:
        if m not in supported:
            raise InputError(None, f"mode {m!r} does not apply to this {engine.variant!r} field")
    wanted = [m for m in wanted if not QUERY_MODES[m].needs_truth]
    if not wanted:
        raise InputError(None, "the 3D-OVS evaluation has no oracle mode: choose composite, explicit, soft or levels")
    num_views = len(engine.scene.cameras)
    cam0 = engine.camera(0)[0]
    labels = read_ovs3d_segmentations(labels_path, size=(cam0.width, cam0.height))
    for view in labels.views:
        if not 0 <= view.view_index < num_views:
            raise InputError(labels.root / view.name, f"view {view.view_index} is not in the scene ({num_views} views)")
    boxes = {"exact": ProtocolConfig(), "scaled": ProtocolConfig.scaled()}
    if on_ready is not None:
        on_ready()
    classes = list(labels.classes)
    C = len(classes)
    scale_modes = [m for m in wanted if QUERY_MODES[m].per_scale]
    blended = [m for m in wanted if QUERY_MODES[m].blends]
    one_map = [m for m in wanted if not QUERY_MODES[m].from_scales]  # answered by the engine directly
    # The modes made from every scale's maps share one pass: the oracle's scorer hook hands them over.
    render_modes = one_map + ([ORACLE.name] if scale_modes or blended else [])
    maps: dict[int, dict[str, dict[str, np.ndarray]]] = {}  # view -> mode -> box -> [C, H, W]
    chosen: dict[int, dict[str, dict[str, list[int]]]] = {}  # view -> mode -> box -> scale per class
    for view in tqdm(labels.views, desc="eval 3D-OVS views", unit="view", disable=not progress):
        vc = engine.render_view(view.view_index, modes=render_modes, rgb=False)
        H, W = vc.height, vc.width
        per_mode: dict[str, dict[str, np.ndarray]] = {}
        picks: dict[str, dict[str, list[int]]] = {}
        for m in one_map:
            rel = engine.query(vc, classes, mode=m).relevancy.float().cpu().numpy()
            per_mode[m] = {b: rel for b in boxes}
        if scale_modes or blended:
            kept = {b: np.zeros((C, H, W), np.float32) for b in boxes}
            levels = {b: [0] * C for b in boxes}
            soft = np.zeros((C, H, W), np.float32)

            def scorer(rel: Any, qi: int) -> np.ndarray:  # [S, H, W] -> [S] (the engine's choice is unused)
                soft[qi] = soft_relevancy(rel.reshape(len(rel), 1, -1))[0].reshape(H, W).float().cpu().numpy()
                r = rel.detach().float().cpu().numpy()
                for b, cfg in boxes.items():
                    size = resolve_box_size(cfg.box_size, W, cfg.box_ref_width)
                    best = int(np.argmax(smoothed_relevancy(r, size).reshape(len(r), -1).max(axis=1)))
                    kept[b][qi] = r[best]
                    levels[b][qi] = best
                return np.zeros(len(r))

            engine.query(vc, classes, mode=ORACLE.name, scorer=scorer)
            for m in scale_modes:
                per_mode[m] = kept
                picks[m] = levels
            for m in blended:
                per_mode[m] = {b: soft for b in boxes}
        maps[view.view_index] = per_mode
        chosen[view.view_index] = picks

    scores: dict[str, dict[str, dict]] = {}
    for m in wanted:
        scores[m] = {}
        for b, cfg in boxes.items():

            def score_fn(i: int, names: list, m: str = m, b: str = b) -> np.ndarray:
                return maps[i][m][b][[classes.index(c) for c in names]]

            s = evaluate_ovs3d(score_fn, labels, num_views, prediction, cfg, empty_union, progress=False).to_dict()
            if m in scale_modes:
                for rec in s["per_view"]:
                    rec["levels"] = list(chosen[rec["view_index"]][m][b])
            scores[m][b] = s
    scale_labels = list(engine.scale_labels)
    first = scores[wanted[0]]
    notes = []
    if first["exact"]["empty_unions"]:
        notes.append(
            f"{first['exact']['empty_unions']} (view, class) pair(s) have an empty ground truth and prediction "
            + ("and score 0 (3D-OVS)" if empty_union == "zero" else "and are left out")
        )
    return {
        "format": OVS3D_FORMAT,
        "protocol": "3D-OVS",
        "scene": Path(getattr(engine.scene, "root", "")).name,
        "run_dir": str(engine.run_dir) if engine.run_dir is not None else "",
        "scene_dir": str(getattr(engine.scene, "root", "")),
        "label_dir": str(labels.root),
        "field": {
            "variant": engine.variant,
            "dim": engine.dim,
            "step": engine.step,
            "num_scales": len(scale_labels),
            "scale_labels": scale_labels,
        },
        "encoder": dict(engine.meta.get("encoder_spec") or {}),
        "classes": classes,
        "views": [v.name for v in labels.views],
        "prediction": prediction,
        "modes": wanted,
        "boxes": {b: {"box_sizes": first[b]["box_sizes"], "majority_radii": first[b]["majority_radii"]} for b in boxes},
        "scores": scores,
        "notes": notes,
        "seconds": time.perf_counter() - t_start,
    }


def ovs3d_markdown(d: dict) -> str:
    """``eval.md`` of a 3D-OVS evaluation (:func:`evaluate_run_ovs3d`)."""
    from .tables import fmt, markdown_table

    boxes = list(d["boxes"])
    title = {b: f"{b} {','.join(map(str, d['boxes'][b]['box_sizes']))} px" for b in boxes}
    f = d["field"]
    rule = (
        "each pixel takes its most relevant class (3D-OVS's closed-set argmax); pixel accuracy as sklearn's "
        "accuracy_score on one-hot rows"
        if d["prediction"] == "argmax"
        else "per class LangSplat's segmentation rule (box smoothing, threshold 0.4, majority filter)"
    )
    out = [
        f"# n2f2 eval (3D-OVS protocol): {d['scene']}\n\n",
        f"- run: `{d['run_dir']}`\n- labels: `{d['label_dir']}` ({len(d['views'])} views, {len(d['classes'])} "
        f"classes)\n- field: {f['variant']}, D = {f['dim']}, k = {f['step']} ({f['num_scales']} scales)\n",
        f"- prediction: {d['prediction']}: {rule}. IoU per (view, class), an empty union scoring 0 (sklearn's "
        "jaccard_score); mIoU = mean over (view, class) pairs. Explicit / levels: per class the scale whose "
        "R' = 0.5 (box(R) + R) peaks highest, under each box size.\n",
    ]
    out += [f"- note: {n}\n" for n in d.get("notes", [])]
    rows = []
    for m in d["modes"]:
        s = d["scores"][m]
        rows.append(
            [m]
            + [fmt(s[b]["miou"], percent=True) for b in boxes]
            + [fmt(s[b]["accuracy"], percent=True) for b in boxes]
        )
    out.append("\n## mIoU and pixel accuracy\n\n")
    out.append(
        markdown_table(
            ["mode"] + [f"mIoU % ({title[b]})" for b in boxes] + [f"pixel acc. % ({title[b]})" for b in boxes], rows
        )
    )
    out.append("\n## Per class (IoU %, mean over views)\n\n")
    rows = [
        [c] + [fmt(d["scores"][m][b]["per_class_iou"][c], percent=True) for m in d["modes"] for b in boxes]
        for c in d["classes"]
    ]
    out.append(markdown_table(["class"] + [f"{m} {title[b]}" for m in d["modes"] for b in boxes], rows))
    return "".join(out)


def write_ovs3d_outputs(d: dict, out_dir: Union[str, Path]) -> dict[str, Path]:
    """``eval.json`` and ``eval.md`` of a 3D-OVS evaluation."""
    from ..io import write_json, write_text

    out = Path(out_dir)
    paths = {"json": out / "eval.json", "md": out / "eval.md"}
    write_text(paths["md"], ovs3d_markdown(d))
    write_json(paths["json"], d)  # last: its presence marks a finished evaluation
    return paths
