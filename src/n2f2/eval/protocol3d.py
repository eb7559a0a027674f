"""The 3D protocol: open-vocabulary object selection on the Gaussians, scored in the labelled
views of LERF-OVS-format labels (the evaluation OpenGaussian introduced and LaGa reports).

Where from. OpenGaussian (Wu et al., NeurIPS 2024; its ``scripts/eval_lerf_iou.py``) scores a
3D language field without rendering features: per text query it selects Gaussians by their own
features, renders the selected Gaussians into each labelled view, and compares the rendered
mask with the label mask. Per (frame, query) pair the IoU; mIoU = mean over pairs; mAcc@0.25 =
fraction of pairs with IoU strictly above 0.25 (its script also prints Acc@0.5). LaGa (Cen et
al. 2025) reports LERF-OVS under the same protocol. The 2D protocol (:mod:`n2f2.eval.protocol`)
instead renders features and post-processes the 2D relevancy map (box filter, threshold,
majority filter); here nothing is smoothed in 2D, so the numbers judge the 3D answer itself.

The rules, per query mode (``composite``, ``explicit``, ``soft``, ``levels``; ``oracle`` is a 2D
bound with no 3D query and is left out):

* **relevancy of each Gaussian**: :meth:`QueryEngine.query_gaussians` (composite: the Gaussian's
  ``W Theta~_i``; explicit / levels: per query the scale whose highest relevancy over the
  Gaussians is largest, the engine's 3D scale rule; soft: every scale weighted by
  ``softmax(peak / tau)`` of those highest relevancies, :mod:`n2f2.query.soft`).
* **selection**: :meth:`QueryEngine.select` with no threshold, the rule ``n2f2 query --3d`` and
  the viewer apply: min-max normalise the Gaussians' relevancy, map [0, 1] to [-1, 1], clip,
  keep ``> 0.4`` (LangSplat's threshold, no box filter). One selection per query, shared by
  every view. (``Protocol3dConfig.threshold`` keeps ``relevancy >= threshold`` instead, as
  ``n2f2 query --3d --threshold`` does.)
* **mask in a view**: :meth:`QueryEngine.render_selection`, the selection indicator rendered
  through all Gaussians (so unselected Gaussians in front occlude the selection), ``> 0.5``: the
  mask ``n2f2 query --3d`` draws. OpenGaussian renders the selected Gaussians alone and keeps
  pixels brighter than 10/255, with no occlusion by the rest of the scene and a far looser cut;
  that is not reproduced.
* **IoU** against the union of the category's polygons, read as the 2D protocol reads them
  (:func:`n2f2.eval.protocol.frame_targets`: objects outside the image dropped and counted,
  labels of another size refused unless ``rescale_labels``). An empty selection scores 0.
* **localization** (ours: OpenGaussian and LaGa report none): the selection-weighted relevancy
  ``r_i * s_i`` (``s_i`` = 1 for a selected Gaussian) rendered into the view as a 1-channel
  feature; a hit when any pixel at its maximum lies inside any of the category's boxes, edges
  included (LangSplat's test, without the box filter: the map is already the 3D answer). An
  empty selection, or one hidden in the view (the map is 0 everywhere), is a miss.

Scene scores per mode: mIoU, mAcc@0.25, mAcc@0.5 and localization accuracy, means over pairs.
Frames outside the scene and two labels for one view are handled as in the 2D runner
(:func:`n2f2.eval.runner.check_label_frames`).
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass
from dataclasses import field as dc_field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Literal, Mapping, Optional, Sequence, Union

import numpy as np

from ..errors import InputError
from .protocol import frame_targets, mask_iou, max_locations, points_in_boxes
from .tables import fmt, markdown_table

if TYPE_CHECKING:
    from ..query.engine import QueryEngine

MODES_3D = ("composite", "explicit", "levels", "soft")  # query modes with a 3D query on the Gaussians
SELECTION_COVER = 0.5  # a pixel is in the selection mask when render_selection > this (n2f2 query --3d)
ACC_IOUS = (0.25, 0.5)  # mAcc@t = fraction of pairs with IoU > t (OpenGaussian)
FORMAT_3D = "n2f2-eval3d-v1"  # eval.json of `n2f2 eval --protocol 3d`


@dataclass(frozen=True)
class Protocol3dConfig:
    """Settings of the 3D protocol. The defaults are the selection rule of ``n2f2 query --3d``."""

    threshold: Optional[float] = None  # absolute relevancy cut; None = the protocol rule of select()
    cover: float = SELECTION_COVER  # selection-mask cut on the rendered selection
    missing_frames: Literal["error", "skip"] = "error"  # label of a frame not in the scene
    rescale_labels: bool = False  # labels drawn at another size: False raises, True rescales
    progress: bool = True

    def __post_init__(self) -> None:
        if self.threshold is not None and not math.isfinite(self.threshold):
            raise ValueError(f"threshold must be finite, got {self.threshold}")
        if not 0.0 <= self.cover < 1.0:
            raise ValueError(f"cover must be in [0, 1), got {self.cover}")
        if self.missing_frames not in ("error", "skip"):
            raise ValueError(f"missing_frames must be 'error' or 'skip', got {self.missing_frames!r}")


@dataclass
class Pair3d:
    """One scored (frame, category) pair."""

    frame: str
    view_index: int
    category: str
    iou: float
    hit: bool
    mask_px: int  # pixels of the rendered selection mask
    gt_px: int  # pixels of the label mask
    loc: Optional[list[int]]  # (x, y) first maximum of the weighted map; None when nothing shows


@dataclass
class Scores3d:
    """Scores of one query mode."""

    mode: str
    pairs: list[Pair3d]
    selections: dict[str, dict]  # query -> {"count": Gaussians selected, "scale": chosen scale or None}
    miou: float
    acc: dict[str, float]  # "0.25" / "0.5" -> fraction of pairs with IoU > t
    loc_accuracy: float
    num_pairs: int
    empty_selections: list[str]  # queries that selected no Gaussian


@dataclass
class Protocol3dResult:
    """Everything :func:`evaluate_protocol3d` measured (``to_dict`` goes into ``eval.json``)."""

    scene: str
    run_dir: str
    label_dir: str
    field: dict  # variant, dim, step
    modes: list[str]
    scores: dict[str, Scores3d]
    num_gaussians: int
    num_frames: int
    skipped_frames: list[str]
    skipped_objects: int
    skipped_categories: int
    rules: dict[str, str]
    config: dict
    notes: list[str] = dc_field(default_factory=list)
    seconds: float = 0.0

    def to_dict(self) -> dict:
        return asdict(self)


RULES = {
    "selection": "QueryEngine.select: min-max normalised Gaussian relevancy mapped to [-1, 1], clipped, > 0.4",
    "mask": "QueryEngine.render_selection (selection indicator rendered through all Gaussians) > 0.5",
    "iou": "IoU of the rendered selection mask and the union of the category's label polygons",
    "acc": "mAcc@t: fraction of pairs with IoU > t (OpenGaussian)",
    "localization": "any maximum of the rendered selection-weighted relevancy inside any of the category's "
    "boxes; empty or hidden selection = miss",
}


def modes_3d(engine: Any, modes: Optional[Sequence[str]] = None) -> list[str]:
    """The modes the 3D protocol scores: ``modes`` (default: every mode the engine supports)
    without ``oracle``, which has no 3D query."""
    supported = list(engine.modes())
    wanted = list(dict.fromkeys(modes or supported))
    for m in wanted:
        if m not in supported:
            raise InputError(None, f"mode {m!r} does not apply to this {engine.variant!r} field")
    out = [m for m in wanted if m in MODES_3D]
    if not out:
        raise InputError(None, "the 3D protocol has no oracle mode: choose composite, explicit, soft or levels")
    return out


def _render_weights(engine: Any, camera: Any, weights: Any) -> np.ndarray:  # weights [N, K] -> [K, H, W]
    """Per-Gaussian values rendered into ``camera`` as features, as render_selection renders its
    indicator (all Gaussians, their own opacities and depth order)."""
    import torch

    from ..render import rasterize

    g = engine.gaussians
    with torch.no_grad():
        out = rasterize(g.means, g.normalized_quats, g.scales, g.opacities, weights, camera)
    return out.features.detach().permute(2, 0, 1).float().cpu().numpy()


def evaluate_protocol3d(
    engine: QueryEngine,  # the run's field, or the lift's LiftEngine
    labels: Sequence[Any],  # list[n2f2.data.labels.FrameLabels]
    *,
    modes: Optional[Sequence[str]] = None,  # default: every 3D mode the engine supports
    config: Protocol3dConfig = Protocol3dConfig(),
    label_dir: Optional[Union[str, Path]] = None,  # named in errors and recorded
    on_ready: Optional[Callable[[], None]] = None,  # called once the inputs are checked
) -> Protocol3dResult:
    """Score ``labels`` under the 3D protocol (see the module docstring)."""
    import torch
    from tqdm import tqdm

    from .runner import check_label_frames

    t_start = time.perf_counter()
    where = Path(label_dir) if label_dir is not None else Path(".")
    if getattr(engine, "gaussians", None) is None:
        raise InputError(None, "the 3D protocol needs Gaussians: this source has features only in 2D views")
    if engine.scene is None:
        raise InputError(engine.run_dir, "the run does not record its scene folder: pass --scene DIR")
    if len(labels) == 0:
        raise InputError(label_dir, "no label frames to evaluate (empty label folder)")
    wanted = modes_3d(engine, modes)
    frames, skipped_frames = check_label_frames(labels, len(engine.scene.cameras), where, config.missing_frames)
    targets: dict[str, list] = {}
    skipped_objects = skipped_categories = 0
    for frame in frames:
        cam = engine.camera(frame.view_index)[0]
        try:
            t, dropped = frame_targets(frame, (cam.height, cam.width), config.rescale_labels)
        except ValueError as e:
            raise InputError(
                where / f"{frame.frame_name}.json", f"{e} (render size; pass --rescale-labels to scale the labels)"
            ) from None
        targets[frame.frame_name] = t
        skipped_objects += dropped
        skipped_categories += len(frame.categories) - len(t)
    queries = list(dict.fromkeys(t.category for ts in targets.values() for t in ts))
    if not queries:
        raise InputError(label_dir, "no (frame, category) pair left to score")
    if on_ready is not None:
        on_ready()

    scores: dict[str, Scores3d] = {}
    for mode in wanted:
        result = engine.query_gaussians(queries, mode)
        relevancy = result.relevancy.float()  # [Q, N]
        chosen = result.chosen_labels
        selected = {q: engine.select(q, config.threshold, mode).bool() for q in queries}  # [N] each
        weights = torch.stack([relevancy[k] * selected[q].to(relevancy) for k, q in enumerate(queries)], dim=1)
        pairs: list[Pair3d] = []
        for frame in tqdm(frames, desc=f"eval 3D {mode}", unit="view", disable=not config.progress):
            present = targets[frame.frame_name]
            if not present:
                continue
            cam = engine.camera(frame.view_index)[0]
            rows = [queries.index(t.category) for t in present]
            weighted = _render_weights(engine, cam, weights[:, rows])  # [K, H, W]
            for k, t in enumerate(present):
                cover = engine.render_selection(selected[t.category], frame.view_index).float().cpu().numpy()
                mask = cover > config.cover
                iou = mask_iou(mask, t.mask)
                m = weighted[k]
                loc = None
                hit = False
                if m.max() > 0.0:
                    maxima = max_locations(m)
                    loc = [int(v) for v in maxima[0]]
                    hit = points_in_boxes(maxima, t.boxes)
                pairs.append(
                    Pair3d(
                        frame.frame_name,
                        frame.view_index,
                        t.category,
                        float(iou),
                        bool(hit),
                        int(mask.sum()),
                        int(t.mask.sum()),
                        loc,
                    )
                )
        ious = np.array([p.iou for p in pairs], dtype=np.float64)
        scores[mode] = Scores3d(
            mode=mode,
            pairs=pairs,
            selections={q: {"count": int(selected[q].sum()), "scale": chosen[k]} for k, q in enumerate(queries)},
            miou=float(ious.mean()),
            acc={str(t): float((ious > t).mean()) for t in ACC_IOUS},
            loc_accuracy=float(np.mean([p.hit for p in pairs])),
            num_pairs=len(pairs),
            empty_selections=[q for q in queries if not bool(selected[q].any())],
        )
    notes = []
    if skipped_frames:
        notes.append(f"{len(skipped_frames)} label frame(s) refer to views not in the scene and were skipped")
    if skipped_objects:
        notes.append(
            f"{skipped_objects} labelled object(s) have a polygon outside the image and were dropped; "
            f"{skipped_categories} (frame, category) pair(s) were left empty and not scored"
        )
    rules = dict(RULES)
    if config.threshold is not None:
        rules["selection"] = f"Gaussian relevancy >= {config.threshold}"
    if config.cover != SELECTION_COVER:
        rules["mask"] = f"QueryEngine.render_selection > {config.cover}"
    return Protocol3dResult(
        scene=Path(getattr(engine.scene, "root", "")).name,
        run_dir=str(engine.run_dir) if engine.run_dir is not None else "",
        label_dir=str(label_dir) if label_dir is not None else "",
        field={"variant": engine.variant, "dim": engine.dim, "step": engine.step},
        modes=wanted,
        scores=scores,
        num_gaussians=int(engine.gaussians.num),
        num_frames=len({p.frame for s in scores.values() for p in s.pairs}),
        skipped_frames=skipped_frames,
        skipped_objects=skipped_objects,
        skipped_categories=skipped_categories,
        rules=rules,
        config=asdict(config),
        notes=notes,
        seconds=time.perf_counter() - t_start,
    )


# ------------------------------------------------------------------------------ reports
def protocol3d_markdown(d: Mapping) -> str:
    """The ``eval.md`` section of a :class:`Protocol3dResult` (as a dict)."""
    modes = list(d["modes"])
    acc_keys = list(next(iter(d["scores"].values()))["acc"])
    out = [
        "\n## 3D protocol: Gaussians selected in 3D, rendered into each labelled view\n\n",
        "OpenGaussian's LERF-OVS evaluation (also reported by LaGa): per query the Gaussians are "
        "selected from their own features, the selection is rendered into each labelled view and "
        "compared with the label mask; no 2D smoothing.\n\n",
    ]
    out += [f"- {k}: {v}\n" for k, v in d["rules"].items()]
    rows = []
    for m in modes:
        s = d["scores"][m]
        rows.append(
            [m, fmt(s["miou"], percent=True)]
            + [fmt(s["acc"][k], percent=True) for k in acc_keys]
            + [fmt(s["loc_accuracy"], percent=True), s["num_pairs"], len(s["empty_selections"])]
        )
    out.append("\n")
    out.append(
        markdown_table(
            ["mode", "mIoU %"] + [f"mAcc@{k} %" for k in acc_keys] + ["loc. %", "pairs", "empty selections"], rows
        )
    )
    out.append(
        f"\n{d['num_frames']} labelled frames, {d['num_gaussians']} Gaussians; skipped frames: "
        f"{len(d['skipped_frames'])}, objects outside the image: {d['skipped_objects']}.\n"
    )
    queries = sorted({q for m in modes for q in d["scores"][m]["selections"]})
    rows = []
    for q in queries:
        row: list = [q]
        for m in modes:
            s = d["scores"][m]
            ious = [p["iou"] for p in s["pairs"] if p["category"] == q]
            sel = s["selections"].get(q, {})
            scale = f" ({sel['scale']})" if sel.get("scale") else ""
            row += [f"{sel.get('count', 0)}{scale}", fmt(float(np.mean(ious)) if ious else math.nan, percent=True)]
        rows.append(row)
    out.append("\n### Per query (Gaussians selected, and mean IoU % over the frames it is labelled in)\n\n")
    out.append(
        markdown_table(
            ["query"] + [h for m in modes for h in (f"{m} selected", f"{m} IoU %")],
            rows,
        )
    )
    for note in d.get("notes", []):
        out.append(f"\n- note: {note}")
    out.append("\n")
    return "".join(out)


def markdown_report_3d(d: Mapping) -> str:
    """``eval.md`` of ``n2f2 eval --protocol 3d`` (the 3D protocol alone)."""
    f = d["field"]
    head = (
        f"# n2f2 eval (3D protocol): {d['scene']}\n\n"
        f"- run: `{d['run_dir']}`\n- labels: `{d['label_dir']}`\n"
        f"- field: {f['variant']}, D = {f['dim']}, k = {f['step']}\n"
    )
    return head + protocol3d_markdown(d)


def write_protocol3d_outputs(result: Protocol3dResult, out_dir: Union[str, Path]) -> dict[str, Path]:
    """``eval.json`` (format ``n2f2-eval3d-v1``) and ``eval.md`` of the 3D protocol alone."""
    from ..io import write_json, write_text

    out = Path(out_dir)
    data = {"format": FORMAT_3D, **result.to_dict()}
    paths = {"json": out / "eval.json", "md": out / "eval.md"}
    write_text(paths["md"], markdown_report_3d(data))
    write_json(paths["json"], data)  # last: its presence marks a finished evaluation
    return paths
