"""The evaluation runner: a trained run + LangSplat-format labels -> every number of the paper's
LERF-OVS tables (Sec. 4.1, appendix Tables 7 and 8, the R@K retrieval figure), written as
``eval.json``, ``eval.md``, PNG plots and raw relevancy ``.npy`` files.

What is measured, per query mode (``composite``, ``explicit``, ``soft``, ``levels`` for a
3-level field, ``oracle``) and per box size:

* **Box sizes, always both.** ``exact`` is LangSplat's protocol as released (30 px mean filter,
  7x7 majority filter), sized for LERF-OVS images about 986 px wide; ``scaled`` is the same
  rules with both pixel sizes scaled to the evaluated width (:meth:`ProtocolConfig.scaled`).
  On small renders (the 160 px demo) the 30 px box erases small parts, so both are reported
  side by side; neither is tuned.
* **Localization accuracy and mIoU** per scene, from :func:`n2f2.eval.protocol.evaluate_scene`.
* **Scale choice of each mode** (the candidate scales are the field's ``floor(D / k)`` prefix
  scales, or the 3 levels of a "levels" field):

  - ``composite``: one map per query (paper Sec. 3.3); no choice.
  - ``soft``: one map per query, the scales' maps weighted by ``softmax(peak / tau)``
    (:mod:`n2f2.query.soft`), computed from the all-scale maps the oracle pass hands over (no
    second render); scored like composite, no choice.
  - ``explicit`` / ``levels``: every scale is handed to the protocol as one of its levels, so the
    choice is LangSplat's own: segmentation uses the scale whose ``R' = 0.5 (box(R) + R)`` has
    the highest maximum, localization the scale whose ``box(R)`` has the highest maximum
    (``protocol.evaluate_frame_category``). The box size of each setting is used for the choice.
  - ``oracle`` (paper Sec. 4.3, "the scale that gives the highest performance for the task in
    question"): per (frame, category) pair, segmentation uses the scale with the best protocol
    IoU and localization the first scale that localizes (any scale whose box-filtered maximum
    lies in a box). It is an upper bound of ``explicit`` / ``levels`` by construction (same
    candidates), *not* of ``composite``, whose map is a blend that is not one of the scales.

  A pair's IoU is computed on its segmentation map and its hit on its localization map: each
  mode's chosen maps are scored by two ``evaluate_scene`` passes (one over the segmentation
  maps, one over the localization maps), so the protocol's bookkeeping (skipped frames and
  objects, label sizes, box sizes used) is the protocol's, not re-implemented here.
* **Simple vs compound queries** (paper Table 7): query types from the scene's
  ``queries.json`` (``"type": "simple" | "compound"``), from a ``--query-types`` JSON, or
  ``"unknown"``. Pair counts of the types add up to the scene's pairs.
* **R@K retrieval** (appendix, K = 1..5): per labelled view the pool is the segment bank's
  segments of that view (every stored segment with at least one pixel). Each segment is scored
  by its mean relevancy (:func:`n2f2.eval.metrics.segment_mean_relevancy`) in the mode's
  segmentation map; segments are ranked per query, ties counted against the query
  (:func:`metrics.segment_ranks`). A segment *matches* the ground truth when its IoU with the
  label's union mask is at least ``retrieval_iou`` (0.5). A (view, query) pair is retrieved at K
  when a matching segment is among the top K (the paper's definition, i.e. hit@K; R@K is
  monotone in K). Pairs with no matching segment in the pool cannot be retrieved by any field:
  they are skipped and counted (``skipped``), not scored 0.
* **Per-query scores** (mean IoU and localization over the frames a query is labelled in), the
  input of the per-query delta between two runs (paper Table 8; ``compare_evals``).
* **AP** (threshold-free): per (frame, query) pair, the average precision of ranking the view's
  pixels by the mode's segmentation map (:func:`n2f2.eval.metrics.average_precision`, ties as
  one threshold) against the exact mask where the scene has one (a generated scene's region
  maps and the ``region_ids`` of its ``queries.json``, at the render size), else the label's
  polygon mask. mAP = mean over pairs; for explicit / levels / oracle it is the AP of the scale
  each box size chose for segmentation. AP separates ranking the right pixels first from the
  protocol's min-max threshold, which mIoU mixes.
* **Query kinds** (part / object / group): from a query's ``"kind"`` in ``queries.json``, else
  from the levels (``regions.json``) of its ``region_ids`` ("mixed" when they differ), else
  "unknown". mIoU, localization and mAP are split by kind.

Bad input (each an :class:`~n2f2.errors.InputError` naming the file, or a counted skip):
an empty or missing label folder; a label whose frame is not a view of the scene (error, or
with ``missing_frames="skip"`` a skip listed in the report); two labels for one view; labels
drawn at another size than the renders (error, or ``rescale_labels=True``); polygons outside
the image (dropped and counted by the protocol); a segment bank of another scene or size.

Memory: the runner renders each labelled view once and keeps, per view, the chosen maps of every
mode (``[Q, H, W]`` float32 each, about 10 per view); the all-scale maps are scored per query and
dropped. On the 160x120 demo that is ~14 MB per view.

(Longer than 600 lines: one pass over the labelled views produces every number above, and this
docstring is their definition; the tables and plots are in :mod:`.reports`.)
"""

from __future__ import annotations

import json
import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, replace
from dataclasses import field as dc_field
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Literal, Mapping, Optional, Sequence, Union

import numpy as np

from ..config import option
from ..errors import InputError
from ..query.modes import MODES, ORACLE, QUERY_MODES
from .metrics import average_precision, per_query_scores, query_deltas, recall_at_k, segment_mean_relevancy
from .protocol import (
    PairRecord,
    ProtocolConfig,
    SceneScores,
    evaluate_frame_category,
    evaluate_scene,
    frame_targets,
    resolve_box_size,
    resolve_majority_radius,
)

BOXES = ("exact", "scaled")  # LangSplat's 30 px box, and the box scaled to the image width
DEFAULT_KS = (1, 2, 3, 4, 5)
RETRIEVAL_IOU = 0.5  # a bank segment matches a label when IoU(segment, union mask) >= this
QUERY_TYPES = ("simple", "compound", "unknown")
QUERY_KINDS = ("part", "object", "group", "mixed", "unknown")  # the hierarchy level a query names
SCALE_MODES = tuple(m for m in MODES if QUERY_MODES[m].per_scale)  # modes that choose a scale per pair
FROM_SCALES = tuple(m for m in MODES if QUERY_MODES[m].from_scales)  # made from the all-scale maps of each query
ONE_MAP_MODES = tuple(m for m in MODES if not QUERY_MODES[m].per_scale)  # one map per query: the same under both boxes


@dataclass(frozen=True)
class EvalConfig:
    """Settings of :func:`evaluate_run`. Defaults: LangSplat's protocol, labels must match.
    Fields declared with option() are flags of `n2f2 eval`."""

    modes: Optional[tuple[str, ...]] = option(
        None,
        help=f"query modes to score ({', '.join(MODES)}); none: every mode the field supports (composite "
        "explicit soft oracle for a nested or flat field, levels oracle for a 3-level one)",
        choices=MODES,
        metavar="MODE",
        nargs="+",
    )
    missing_frames: Literal["error", "skip"] = "error"  # label of a frame not in the scene (skips counted)
    rescale_labels: bool = False  # labels drawn at another size: False raises, True rescales
    ks: tuple[int, ...] = DEFAULT_KS  # R@K cut-offs
    retrieval_iou: float = RETRIEVAL_IOU  # segment/label IoU for a retrieval match
    progress: bool = True

    def protocols(self) -> dict[str, ProtocolConfig]:
        """The two protocol settings every number is reported under."""
        return {
            "exact": ProtocolConfig(missing_frames=self.missing_frames, rescale_labels=self.rescale_labels),
            "scaled": ProtocolConfig.scaled(missing_frames=self.missing_frames, rescale_labels=self.rescale_labels),
        }


@dataclass
class RetrievalSummary:
    """R@K of one (mode, box) over all labelled (view, query) pairs."""

    ks: list[int]
    recall: dict[int, float]  # K -> fraction of scored pairs retrieved at K
    mean_first_rank: float
    num_pairs: int  # scored pairs (a matching segment is in the pool)
    first_ranks: dict[str, int]  # "frame/query" -> rank of the best matching segment
    skipped: list[str] = dc_field(default_factory=list)  # pairs with no matching segment
    iou_threshold: float = RETRIEVAL_IOU
    pool_sizes: dict[str, int] = dc_field(default_factory=dict)  # frame -> segments in the pool


@dataclass
class EvalResult:
    """Everything :func:`evaluate_run` measured (``to_dict`` is ``eval.json``)."""

    scene: str
    run_dir: str
    scene_dir: str
    label_dir: str
    bank_dir: Optional[str]
    encoder: dict  # name, description (honest: e.g. "captions", not CLIP), spec
    field: dict  # variant, dim, step, scale labels
    modes: list[str]
    boxes: dict[str, dict]  # box -> {"box_sizes", "majority_radii", "config"}
    scores: dict[str, dict[str, SceneScores]]  # mode -> box -> scores
    split: dict[str, dict[str, dict[str, dict]]]  # mode -> box -> type -> {pairs, miou, ...}
    retrieval: dict[str, dict[str, RetrievalSummary]]  # mode -> box -> R@K
    per_query: dict[str, dict[str, dict[str, dict]]]  # mode -> box -> query -> {iou, hit, ...}
    query_types: dict[str, str]  # query -> simple | compound | unknown
    query_types_source: str
    views: list[dict]  # per labelled view: index, name, held out from training?, timings
    relevancy_files: dict[str, dict[str, str]] = dc_field(default_factory=dict)  # frame -> query -> path
    relevancy_mode: Optional[str] = None
    # mode -> box -> {"map", "pairs": [{"frame", "query", "ap", "mask"}]}: threshold-free AP
    ap: dict[str, dict[str, dict]] = dc_field(default_factory=dict)
    # mode -> box -> kind -> {pairs, queries, miou, loc_accuracy, map}
    kinds: dict[str, dict[str, dict[str, dict]]] = dc_field(default_factory=dict)
    query_kinds: dict[str, str] = dc_field(default_factory=dict)  # query -> part | object | group | ...
    query_kinds_source: str = ""
    budget: Optional[dict] = None  # the loss budget (n2f2.eval.budget), when asked for
    protocol3d: Optional[dict] = None  # the 3D protocol (n2f2.eval.protocol3d), when asked for
    notes: list[str] = dc_field(default_factory=list)
    seconds: float = 0.0

    def to_dict(self) -> dict:
        d = asdict(self)
        d["format"] = "n2f2-eval-v1"
        if d["protocol3d"] is None:  # only with --protocol both: eval.json is otherwise unchanged
            del d["protocol3d"]
        d["scores"] = {m: {b: s.to_dict() for b, s in by.items()} for m, by in self.scores.items()}
        return d


# ------------------------------------------------------------------------------ inputs
def read_query_types(path: Union[str, Path]) -> dict[str, str]:
    """Query -> type from a ``queries.json`` (``{"queries": [{"query", "type"}]}``) or a plain
    ``{"query": "simple" | "compound"}`` mapping."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as e:
        raise InputError(path, f"cannot read query types ({e})") from None
    except json.JSONDecodeError as e:
        raise InputError(path, f"not valid JSON ({e.msg} at line {e.lineno})") from None
    if isinstance(data, dict) and isinstance(data.get("queries"), list):
        items = []
        for k, q in enumerate(data["queries"]):
            if not isinstance(q, dict) or not isinstance(q.get("query"), str):
                raise InputError(path, f"queries[{k}] must be an object with a 'query' string")
            items.append((q["query"], q.get("type", "unknown")))
    elif isinstance(data, dict):
        items = list(data.items())
    else:
        raise InputError(path, 'query types must be {"queries": [...]} or {query: type}')
    out = {}
    for query, kind in items:
        if kind not in QUERY_TYPES:
            raise InputError(path, f"query {query!r} has type {kind!r}; use one of {', '.join(QUERY_TYPES)}")
        out[str(query)] = str(kind)
    return out


def read_query_kinds(path: Union[str, Path]) -> dict[str, str]:
    """Query -> kind (part / object / group / mixed) from a ``queries.json``: a query's
    ``"kind"``, else the level names (``regions.json`` beside it) of its ``region_ids``. Queries
    with neither are left out (their kind is "unknown"); a file without that information gives
    an empty mapping."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return {}
    if not isinstance(data, dict) or not isinstance(data.get("queries"), list):
        return {}
    levels: dict[int, str] = {}
    regions_path = path.parent / "regions.json"
    if regions_path.is_file():
        try:
            regions = json.loads(regions_path.read_text())
            names = list(regions.get("levels", ["part", "object", "group"]))
            levels = {
                int(r["id"]): (names[int(r["level"])] if int(r["level"]) < len(names) else "unknown")
                for r in regions.get("regions", [])
            }
        except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
            raise InputError(regions_path, f"cannot read the region levels ({e})") from None
    out = {}
    for q in data["queries"]:
        if not isinstance(q, dict) or not isinstance(q.get("query"), str):
            continue
        if isinstance(q.get("kind"), str):
            kind = q["kind"]
        else:
            found = {levels.get(int(r), "unknown") for r in q.get("region_ids") or [] if isinstance(r, int)}
            if not found:
                continue
            kind = found.pop() if len(found) == 1 else "mixed"
        if kind not in QUERY_KINDS:
            raise InputError(path, f"query {q['query']!r} has kind {kind!r}; use one of {', '.join(QUERY_KINDS)}")
        out[q["query"]] = kind
    return out


class ExactMasks:
    """Exact per-query masks of a generated scene's views (region maps + ``queries.json``
    region ids); empty for a scene without them or a render of another size."""

    def __init__(self, scene: Any) -> None:
        self.gt = getattr(scene, "ground_truth", None)
        self.region_ids: dict[str, list[int]] = {}
        self.regions: list = []
        if self.gt is None:
            return
        try:
            self.region_ids = {
                q["query"]: [int(r) for r in q["region_ids"]]
                for q in self.gt.queries
                if isinstance(q, dict) and q.get("region_ids")
            }
            self.regions = list(self.gt.regions["regions"])
        except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError):
            self.region_ids, self.regions = {}, []

    def masks(
        self, view_index: int, queries: Sequence[str], shape: tuple[int, int]
    ) -> dict[str, np.ndarray]:  # query -> [H, W] bool
        wanted = [q for q in queries if q in self.region_ids]
        if not wanted or self.gt is None:
            return {}
        from ..data.synthetic import query_mask

        try:
            reg = np.asarray(self.gt.region_ids(view_index))  # [3, H, W]
        except OSError:
            return {}
        if reg.shape[1:] != tuple(shape):
            return {}
        return {q: query_mask(reg, self.regions, self.region_ids[q]) for q in wanted}


def check_label_frames(
    labels: Sequence[Any], num_views: int, label_dir: Path, missing_frames: str
) -> tuple[list[Any], list[str]]:
    """(frames to render, names of skipped frames). Fails before any rendering, naming the label
    file, on a frame outside the scene (unless ``missing_frames="skip"``) or two labels for one
    view; the protocol applies the same rules again when it scores."""
    keep, skipped, seen = [], [], {}
    for frame in labels:
        path = label_dir / f"{frame.frame_name}.json"
        idx = frame.view_index
        if idx in seen:
            raise InputError(path, f"view {idx} is labelled twice ({seen[idx]} and {frame.frame_name})")
        seen[idx] = frame.frame_name
        if not 0 <= idx < num_views:
            if missing_frames == "skip":
                skipped.append(frame.frame_name)
                continue
            raise InputError(
                path,
                f"label {frame.frame_name!r} refers to view {idx}, but the scene has "
                f"{num_views} views (frame_00001 is view 0); pass --skip-missing-frames "
                "to leave it out",
            )
        keep.append(frame)
    return keep, skipped


# ------------------------------------------------------------------------------ per view
@dataclass
class _ViewMaps:
    """Chosen maps of one view: mode -> box -> {"seg" | "loc": [K, H, W]}, and the choices."""

    frame: str
    categories: list[str]
    maps: dict[str, dict[str, dict[str, np.ndarray]]]
    # mode -> box -> category -> (seg scale, loc scale, IoU of every scale)
    choices: dict[str, dict[str, dict[str, tuple[int, int, list[float]]]]]
    all_scales: Optional[np.ndarray] = None  # [K, S, H, W] for a levels field's npy output


MAX_SCORING_IN_FLIGHT = 4  # (query, box) stacks of [S, H, W] maps queued for scoring at once


@lru_cache(maxsize=None)
def _scoring_executor() -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=2, thread_name_prefix="n2f2-scoring")


def _scale_maps(
    engine: Any,
    view: Any,
    categories: list[str],
    targets: dict,
    modes: list[str],
    protocols: dict[str, ProtocolConfig],
    keep_all: bool,
) -> tuple[dict, dict, Optional[np.ndarray]]:
    """Score every scale of every labelled category once (through the engine's oracle scorer
    hook, which hands over the ``[S, H, W]`` maps of one query) and keep each mode's chosen maps,
    and the soft map (:func:`n2f2.query.soft.soft_relevancy`) made from them."""
    from ..query.soft import soft_relevancy

    H, W = view.height, view.width
    K = len(categories)
    wanted = [m for m in modes if m in SCALE_MODES]
    maps = {
        m: {b: {"seg": np.zeros((K, H, W), np.float32), "loc": np.zeros((K, H, W), np.float32)} for b in protocols}
        for m in wanted
    }
    choices: dict = {m: {b: {} for b in protocols} for m in wanted}
    stacks: list = [None] * K
    blended = [m for m in modes if QUERY_MODES[m].blends]
    soft = np.zeros((K, H, W), np.float32) if blended else None
    if soft is not None:
        for m in blended:
            maps[m] = {b: {"seg": soft, "loc": soft} for b in protocols}  # one map, as composite's

    def score(r: np.ndarray, qi: int, b: str) -> None:  # one query's [S, H, W] maps under box setting b
        target = targets[categories[qi]]
        cfg = protocols[b]
        size = resolve_box_size(cfg.box_size, W, cfg.box_ref_width)
        radius = resolve_majority_radius(cfg.majority_radius, W, cfg.box_ref_width)
        res = evaluate_frame_category(r, target.mask, target.boxes, size, cfg.threshold, radius)
        hits = res.hit_per_level
        by_protocol = (res.seg_level, res.loc_level)
        by_truth = (int(np.argmax(res.iou_per_level)), hits.index(True) if any(hits) else res.loc_level)
        for m in wanted:
            seg, loc = by_truth if QUERY_MODES[m].needs_truth else by_protocol
            maps[m][b]["seg"][qi] = r[seg]
            maps[m][b]["loc"][qi] = r[loc]
            choices[m][b][categories[qi]] = (seg, loc, res.iou_per_level)

    # The protocol's filters (OpenCV, NumPy: they release the GIL) of one query run on worker
    # threads while the engine computes the next query's maps; each (query, box) writes its own
    # slots, so the results are those of one loop. At most MAX_SCORING_IN_FLIGHT stacks wait.
    pending: list = []

    def scorer(rel: Any, qi: int) -> np.ndarray:  # rel [S, H, W] -> [S] (the engine's choice is unused)
        if soft is not None:
            soft[qi] = soft_relevancy(rel.reshape(len(rel), 1, -1))[0].reshape(H, W).float().cpu().numpy()
        r = rel.detach().float().cpu().numpy().copy()  # the engine may reuse its buffer for the next query
        if keep_all:
            stacks[qi] = r
        if targets.get(categories[qi]) is None or not wanted:  # not scored (objects outside the image), or no choice
            return np.zeros(len(r))
        while len(pending) >= MAX_SCORING_IN_FLIGHT:
            pending.pop(0).result()
        pending.extend(_scoring_executor().submit(score, r, qi, b) for b in protocols)
        return np.zeros(len(r))

    try:
        engine.query(view, categories, mode=ORACLE.name, scorer=scorer)
    finally:
        for job in pending:
            job.result()  # re-raises a worker's error here
    all_scales = np.stack(stacks, axis=0) if keep_all else None  # [K, S, H, W]
    return maps, choices, all_scales


# ------------------------------------------------------------------------------ retrieval
def segment_label_iou(
    layers: np.ndarray,  # [L, H, W] int segment ids, -1 = none
    gt: np.ndarray,  # [H, W] bool union mask of a label
    num_segments: int,
) -> np.ndarray:  # [S] IoU of every segment with the mask (0 for an empty segment)
    """IoU of each bank segment with a label mask, from id counts (no per-segment masks)."""
    area = np.zeros(num_segments, np.int64)
    inter = np.zeros(num_segments, np.int64)
    for layer in np.asarray(layers):
        ids = layer[layer >= 0]
        area += np.bincount(ids, minlength=num_segments)
        inter += np.bincount(layer[(layer >= 0) & gt], minlength=num_segments)
    union = area + int(gt.sum()) - inter
    return np.where(union > 0, inter / np.maximum(union, 1), 0.0)


@dataclass
class _RetrievalAcc:
    first_ranks: dict[str, int] = dc_field(default_factory=dict)
    skipped: list[str] = dc_field(default_factory=list)
    pool_sizes: dict[str, int] = dc_field(default_factory=dict)

    def add(
        self,
        frame: str,
        relevancy: np.ndarray,  # [K, H, W]
        categories: list[str],
        positives: list[list[int]],
        layers: np.ndarray,
        num_segments: int,
        ks: Sequence[int],
    ) -> None:
        scores, areas = segment_mean_relevancy(relevancy, layers, num_segments)  # [K, S]
        names = [f"{frame}/{c}" for c in categories]
        r = recall_at_k(scores, positives, ks=ks, queries=names)
        self.first_ranks.update({q.query: q.first_rank for q in r.per_query})
        self.skipped += r.skipped
        self.pool_sizes[frame] = int((areas > 0).sum())

    def summary(self, ks: Sequence[int], iou: float) -> RetrievalSummary:
        ranks = np.asarray(list(self.first_ranks.values()), dtype=np.float64)
        recall = {int(k): (float((ranks <= k).mean()) if ranks.size else math.nan) for k in ks}
        return RetrievalSummary(
            list(map(int, ks)),
            recall,
            float(ranks.mean()) if ranks.size else math.nan,
            int(ranks.size),
            dict(self.first_ranks),
            list(self.skipped),
            iou,
            dict(self.pool_sizes),
        )


# ------------------------------------------------------------------------------ scoring
def _stored(per_view: Mapping[int, _ViewMaps], mode: str, box: str, kind: str):
    """The protocol's ``relevancy_fn`` over the kept maps: (view, categories) -> [1, K, H, W]."""

    def relevancy_fn(i: int, categories: list) -> np.ndarray:
        vm = per_view[i]
        return vm.maps[mode][box][kind][[vm.categories.index(c) for c in categories]][None]

    return relevancy_fn


def _combine(
    seg: SceneScores, loc: SceneScores, choices: Optional[dict[tuple[str, str], tuple[int, int, list[float]]]]
) -> SceneScores:
    """One mode's scores: IoU from the segmentation-map pass, hit from the localization-map pass;
    the levels recorded are the chosen scales (and every scale's IoU) of the mode."""
    pairs = []
    for ps, pl in zip(seg.pairs, loc.pairs):
        if (ps.frame, ps.category) != (pl.frame, pl.category):
            raise RuntimeError("segmentation and localization passes scored different pairs")
        if choices is None:
            pairs.append(replace(ps, hit=pl.hit))
        else:
            s, l_, ious = choices[(ps.frame, ps.category)]
            pairs.append(replace(ps, hit=pl.hit, seg_level=s, loc_level=l_, iou_per_level=list(ious)))
    return replace(seg, pairs=pairs, loc_accuracy=sum(p.hit for p in pairs) / len(pairs))


def split_scores(pairs: Sequence[PairRecord], types: Mapping[str, str]) -> dict[str, dict]:
    """mIoU and localization accuracy per query type (paper Table 7); types with no pair are
    listed with ``pairs: 0`` and NaN scores."""
    out = {}
    for kind in QUERY_TYPES:
        sel = [p for p in pairs if types.get(p.category, "unknown") == kind]
        out[kind] = {
            "pairs": len(sel),
            "queries": sorted({p.category for p in sel}),
            "miou": float(np.mean([p.iou for p in sel])) if sel else math.nan,
            "loc_accuracy": float(np.mean([p.hit for p in sel])) if sel else math.nan,
        }
    return out


def _per_query(
    pairs: Sequence[PairRecord], types: Mapping[str, str], ap_pairs: Sequence[Mapping] = ()
) -> dict[str, dict]:
    iou = per_query_scores(pairs, "iou")
    hit = per_query_scores(pairs, "hit")
    frames: dict[str, int] = {}
    for p in pairs:
        frames[p.category] = frames.get(p.category, 0) + 1
    aps: dict[str, list[float]] = {}
    for p in ap_pairs:
        aps.setdefault(p["query"], []).append(p["ap"])
    return {
        q: {
            "iou": iou[q],
            "hit": hit[q],
            "frames": frames[q],
            "type": types.get(q, "unknown"),
            "ap": float(np.mean(aps[q])) if q in aps else math.nan,
        }
        for q in iou
    }


# ------------------------------------------------------------------------------ the runner
@dataclass
class _Evaluation:
    """What one evaluation reads (the engine, the settings, the labels' queries and the bank)
    and what its pass over the labelled views fills in, view by view."""

    engine: Any  # the query engine of the run (or the one given)
    config: EvalConfig
    run_dir: Path
    label_dir: Path
    scene: Any  # the engine's scene
    modes: list[str]
    protocols: dict[str, ProtocolConfig]
    notes: list[str]
    types: dict[str, str]  # query -> simple | compound
    types_source: str
    kinds: dict[str, str]  # query -> part | object | group | ...
    kinds_source: str
    exact: ExactMasks
    bank: Any  # the opened SegmentBank for R@K, or None
    bank_path: Optional[str]
    all_categories: list[str]  # every labelled query, in order of first appearance
    slugs: dict[str, str]  # query -> its relevancy file's name
    npy_mode: Any  # the QueryMode whose maps are written as .npy, or None
    one_map: list[str]  # modes answered by the engine directly
    render_modes: list[str]  # what each view is rendered for
    heldout: set[int]  # views held out from training
    train_views: Optional[list]  # as the run records them; None: unknown
    relevancy_dir: Optional[Path]
    per_view: dict[int, _ViewMaps] = dc_field(default_factory=dict)
    retrieval: dict[str, dict[str, _RetrievalAcc]] = dc_field(default_factory=dict)  # mode -> box -> R@K so far
    ap_pairs: dict[str, dict[str, list[dict]]] = dc_field(default_factory=dict)  # mode -> box -> AP per pair
    view_info: list[dict] = dc_field(default_factory=list)  # per labelled view: index, name, timings
    relevancy_files: dict[str, dict[str, str]] = dc_field(default_factory=dict)  # frame -> query -> path


def evaluate_run(
    run_dir: Union[str, Path],
    label_dir: Union[str, Path],
    *,
    scene: Optional[Union[str, Path]] = None,  # default: the scene recorded in the run
    bank: Optional[Union[str, Path]] = None,  # default: the bank recorded in the run; R@K needs one
    query_types: Optional[Union[str, Path, Mapping[str, str]]] = None,  # default: SCENE/queries.json
    config: EvalConfig = EvalConfig(),
    query_config: Any = None,  # n2f2.query.QueryConfig (canonical phrases, temperature, negatives)
    device: str = "cpu",
    encoder: Any = None,  # text encoder override (tests); default: the one the field was trained with
    relevancy_dir: Optional[Union[str, Path]] = None,  # write raw float32 maps here (see module doc)
    on_ready: Optional[Callable[[], None]] = None,  # called once every input is checked, before any write
    engine: Any = None,  # a ready query engine (the lift, the teacher's features) instead of the run's field
) -> EvalResult:
    """Evaluate a trained run on LangSplat-format labels (see the module docstring).
    ``on_ready`` runs once every input is read and checked, before the first file is written
    (``n2f2 eval --force`` removes the previous results there). ``engine`` scores another
    source of features (:mod:`n2f2.eval.budget`) with exactly the same code."""
    from tqdm import tqdm

    from ..data.labels import read_label_dir
    from ..query.engine import QueryEngine
    from ..query.outputs import unique_slugs

    t_start = time.perf_counter()
    if config.missing_frames not in ("error", "skip"):
        raise ValueError(f"missing_frames must be 'error' or 'skip', got {config.missing_frames!r}")
    run_dir, label_dir = Path(run_dir), Path(label_dir)
    labels = read_label_dir(label_dir)  # InputError on a missing folder or one with no frame_*.json
    if engine is None:
        engine = QueryEngine.from_run(run_dir, device=device, scene=scene, config=query_config, encoder=encoder)
    if engine.scene is None:
        raise InputError(run_dir, "the run does not record its scene folder: pass --scene DIR")
    scene_obj = engine.scene
    num_views = len(scene_obj.cameras)
    modes = _checked_modes(engine, config, run_dir)
    protocols = config.protocols()
    frames, skipped_frames = check_label_frames(labels, num_views, label_dir, config.missing_frames)
    notes: list[str] = []
    if skipped_frames:
        notes.append(
            f"{len(skipped_frames)} label frame(s) refer to views not in the scene and were "
            f"skipped: {', '.join(skipped_frames)}"
        )
    types, types_source = _query_types(query_types, scene_obj)
    kinds, kinds_source = _query_kinds(query_types, scene_obj)
    exact = ExactMasks(scene_obj)
    bank_obj, bank_path = _open_bank(bank, engine, scene_obj, notes)

    all_categories = list(dict.fromkeys(c for f in frames for c in f.categories))
    one_map = [m for m in modes if not QUERY_MODES[m].from_scales]  # answered by the engine directly
    ev = _Evaluation(
        engine=engine,
        config=config,
        run_dir=run_dir,
        label_dir=label_dir,
        scene=scene_obj,
        modes=modes,
        protocols=protocols,
        notes=notes,
        types=types,
        types_source=types_source,
        kinds=kinds,
        kinds_source=kinds_source,
        exact=exact,
        bank=bank_obj,
        bank_path=bank_path,
        all_categories=all_categories,
        slugs=dict(zip(all_categories, unique_slugs(all_categories))),
        npy_mode=next((QUERY_MODES[m] for m in MODES if m in modes and QUERY_MODES[m].writes_npy), None),
        one_map=one_map,
        # The modes made from every scale's maps share one pass: the oracle's scorer hook hands them over.
        render_modes=one_map + ([ORACLE.name] if any(m in FROM_SCALES for m in modes) else []),
        heldout=set(int(v) for v in engine.meta.get("heldout_views", []) or []),
        train_views=engine.meta.get("train_views"),
        relevancy_dir=None if relevancy_dir is None else Path(relevancy_dir),
        retrieval={m: {b: _RetrievalAcc() for b in protocols} for m in modes},
        ap_pairs={m: {b: [] for b in protocols} for m in modes},
    )
    frame_gt = _frame_targets(engine, frames, config.rescale_labels, label_dir)
    if on_ready is not None:
        on_ready()
    for frame in tqdm(frames, desc="eval views", unit="view", disable=not config.progress):
        if not frame.categories:
            continue
        _evaluate_view(ev, frame, frame_gt[frame.frame_name])

    scores = _protocol_scores(ev, labels, num_views)
    return _eval_result(ev, scores, encoder, t_start)


def _checked_modes(engine: Any, config: EvalConfig, run_dir: Path) -> list[str]:
    """The modes to score: ``config.modes`` (default: every mode the field supports), each one
    the field supports (InputError otherwise)."""
    supported = list(engine.modes())
    modes = list(dict.fromkeys(config.modes or supported))
    for m in modes:
        if m not in supported:
            raise InputError(
                run_dir / "field.pt",
                f"mode {m!r} does not apply to this {engine.variant!r} field (it supports {', '.join(supported)})",
            )
    return modes


def _query_types(query_types: Optional[Union[str, Path, Mapping[str, str]]], scene: Any) -> tuple[dict[str, str], str]:
    """(query -> type, where from): the given file or mapping, the scene's queries.json, else
    none (every query "unknown")."""
    types: dict[str, str] = {}
    types_source = "none (all queries 'unknown')"
    if query_types is not None:
        types = dict(query_types) if isinstance(query_types, Mapping) else read_query_types(query_types)
        types_source = "given mapping" if isinstance(query_types, Mapping) else str(query_types)
    elif (Path(scene.root) / "queries.json").is_file():
        types = read_query_types(Path(scene.root) / "queries.json")
        types_source = str(Path(scene.root) / "queries.json")
    return types, types_source


def _query_kinds(query_types: Optional[Union[str, Path, Mapping[str, str]]], scene: Any) -> tuple[dict[str, str], str]:
    """(query -> kind, where from): part / object / group from the first of the given types
    file and the scene's queries.json that has any (a query's "kind" or its regions' levels)."""
    kinds: dict[str, str] = {}
    kinds_source = "none (all queries 'unknown')"
    for candidate in ([query_types] if isinstance(query_types, (str, Path)) else []) + [
        Path(scene.root) / "queries.json"
    ]:
        if Path(candidate).is_file():
            kinds = read_query_kinds(candidate)
            if kinds:
                kinds_source = str(candidate)
                break
    return kinds, kinds_source


def _open_bank(
    bank: Optional[Union[str, Path]], engine: Any, scene: Any, notes: list[str]
) -> tuple[Any, Optional[str]]:
    """(the segment bank for R@K, its path): the given one or the run's, checked against the
    scene; (None, None) with a note in ``notes`` when there is none."""
    bank_obj, bank_path = None, None
    bank_arg = bank if bank is not None else engine.meta.get("bank")
    if bank_arg:
        from ..segments.bank import SegmentBank

        if bank is None and not Path(bank_arg).is_dir():
            notes.append(f"R@K not computed: the run's segment bank {bank_arg} does not exist (pass --bank)")
        else:
            bank_obj, bank_path = SegmentBank.open(bank_arg), str(bank_arg)
            bank_obj.validate_against(scene)
    else:
        notes.append("R@K not computed: the run records no segment bank (pass --bank)")
    return bank_obj, bank_path


def _frame_targets(engine: Any, frames: Sequence[Any], rescale_labels: bool, label_dir: Path) -> dict[str, list]:
    """Ground truth of every frame at its render size, before any rendering, so a label of the
    wrong size fails fast (InputError naming the label file)."""
    frame_gt: dict[str, list] = {}
    for frame in frames:
        camera = engine.camera(frame.view_index)[0]
        try:
            frame_gt[frame.frame_name] = frame_targets(frame, (camera.height, camera.width), rescale_labels)[0]
        except ValueError as e:
            raise InputError(
                label_dir / f"{frame.frame_name}.json", f"{e} (render size; pass --rescale-labels to scale the labels)"
            ) from None
    return frame_gt


def _evaluate_view(ev: _Evaluation, frame: Any, target_list: list) -> None:
    """Render one labelled view, keep each mode's maps of its queries, and add its AP pairs,
    relevancy files, retrieval ranks and timings to ``ev``."""
    idx = frame.view_index
    categories = frame.categories
    targets = {t.category: t for t in target_list}
    t0 = time.perf_counter()
    view = ev.engine.render_view(idx, modes=ev.render_modes, rgb=False)
    t1 = time.perf_counter()
    maps: dict = {}
    choices: dict = {}
    for m in ev.one_map:
        rel = ev.engine.query(view, categories, mode=m).relevancy.float().cpu().numpy()
        maps[m] = {b: {"seg": rel, "loc": rel} for b in ev.protocols}
    all_scales = None
    if any(m in FROM_SCALES for m in ev.modes):
        smaps, choices, all_scales = _scale_maps(
            ev.engine,
            view,
            categories,
            targets,
            ev.modes,
            ev.protocols,
            keep_all=(ev.npy_mode is not None and ev.npy_mode.per_scale and ev.relevancy_dir is not None),
        )
        maps.update(smaps)
    t2 = time.perf_counter()
    ev.per_view[idx] = _ViewMaps(frame.frame_name, categories, maps, choices)
    _add_ap_pairs(ev, frame.frame_name, idx, view, categories, targets, maps)
    if ev.relevancy_dir is not None and ev.npy_mode is not None:
        _write_relevancy(ev, view, categories, maps, all_scales)
    if ev.bank is not None and target_list:
        _add_retrieval(ev, frame.frame_name, idx, view, categories, targets, maps)
    ev.view_info.append(
        {
            "view_index": idx,
            "frame": frame.frame_name,
            "name": view.name,
            "heldout": (idx in ev.heldout) if ev.train_views is not None else None,
            "categories": len(categories),
            "render_s": t1 - t0,
            "query_s": t2 - t1,
        }
    )


def _add_ap_pairs(
    ev: _Evaluation, frame: str, idx: int, view: Any, categories: list[str], targets: dict, maps: dict
) -> None:
    """AP of each scored pair of the view against the exact mask (else the polygon mask)."""
    exact_masks = ev.exact.masks(idx, [c for c in categories if c in targets], (view.height, view.width))
    for k, c in enumerate(categories):
        if c not in targets:
            continue
        mask, kind = (
            (exact_masks[c], "exact") if c in exact_masks and exact_masks[c].any() else (targets[c].mask, "polygon")
        )
        for m in ev.modes:
            done: dict[int, float] = {}  # the same map under both boxes is ranked once
            for b in ev.protocols:
                seg = maps[m][b]["seg"]
                key = id(seg)
                if key not in done:
                    done[key] = average_precision(seg[k], mask)
                ev.ap_pairs[m][b].append({"frame": frame, "query": c, "ap": done[key], "mask": kind})


def _write_relevancy(
    ev: _Evaluation, view: Any, categories: list[str], maps: dict, all_scales: Optional[np.ndarray]
) -> None:
    """The npy mode's map of each query of the view (every scale's for a per-scale mode) as a
    float32 ``.npy`` in ``relevancy_dir/<view>/``."""
    from ..io import write_npy

    assert ev.relevancy_dir is not None and ev.npy_mode is not None  # the caller's condition
    files = ev.relevancy_files.setdefault(view.name, {})
    for k, c in enumerate(categories):
        path = Path(ev.relevancy_dir) / view.name / f"{ev.slugs[c]}.npy"
        if not ev.npy_mode.per_scale:
            arr = maps[ev.npy_mode.name]["exact"]["seg"][k]
        else:
            assert all_scales is not None  # a per-scale npy_mode with relevancy_dir: _scale_maps kept them
            arr = all_scales[k]
        write_npy(path, np.ascontiguousarray(arr, dtype=np.float32))
        files[c] = str(path)


def _add_retrieval(
    ev: _Evaluation, frame: str, idx: int, view: Any, categories: list[str], targets: dict, maps: dict
) -> None:
    """Rank the view's bank segments for each scored query, per mode and box (R@K)."""
    rec = ev.bank.record(ev.bank.index(ev.scene.image_names[idx]))
    layers = np.asarray(rec.layers)
    if layers.shape[1:] != (view.height, view.width):
        assert ev.bank_path is not None  # set together with the bank
        raise InputError(
            Path(ev.bank_path) / "bank.json",
            f"segments of {view.name} are {layers.shape[2]}x{layers.shape[1]} but the "
            f"render is {view.width}x{view.height}",
        )
    S = rec.num_segments
    scored = [c for c in categories if c in targets]
    positives = [
        np.flatnonzero(segment_label_iou(layers, targets[c].mask, S) >= ev.config.retrieval_iou).tolist()
        for c in scored
    ]
    rows = [categories.index(c) for c in scored]
    for m in ev.modes:
        for b in ev.protocols:
            ev.retrieval[m][b].add(frame, maps[m][b]["seg"][rows], scored, positives, layers, S, ev.config.ks)


def _protocol_scores(ev: _Evaluation, labels: Sequence[Any], num_views: int) -> dict[str, dict[str, SceneScores]]:
    """Protocol passes over the kept maps, per mode and box: segmentation maps -> IoU,
    localization maps -> hits, combined with the scales each mode chose."""
    scores: dict[str, dict[str, SceneScores]] = {}
    for m in ev.modes:
        scores[m] = {}
        for b, cfg in ev.protocols.items():
            seg = evaluate_scene(
                _stored(ev.per_view, m, b, "seg"), labels, num_views, cfg, ev.label_dir, progress=False
            )
            loc = evaluate_scene(
                _stored(ev.per_view, m, b, "loc"), labels, num_views, cfg, ev.label_dir, progress=False
            )
            ch = None
            if m in SCALE_MODES:
                ch = {(vm.frame, c): v for vm in ev.per_view.values() for c, v in vm.choices[m][b].items()}
            scores[m][b] = _combine(seg, loc, ch)
    return scores


def _eval_result(
    ev: _Evaluation, scores: dict[str, dict[str, SceneScores]], encoder: Any, t_start: float
) -> EvalResult:
    """The :class:`EvalResult` of the scores and what the pass collected, with the closing
    notes (dropped objects, held-out views, the teacher)."""
    from ..query.composite import temperature_name

    engine, config, modes, protocols, notes = ev.engine, ev.config, ev.modes, ev.protocols, ev.notes
    any_scores = scores[modes[0]]
    boxes = {
        b: {
            "box_sizes": any_scores[b].box_sizes,
            "majority_radii": any_scores[b].majority_radii,
            "config": asdict(protocols[b]),
        }
        for b in protocols
    }
    ref = any_scores["exact"]
    if ref.skipped_objects:
        notes.append(
            f"{ref.skipped_objects} labelled object(s) have a polygon outside the image and were "
            f"dropped; {ref.skipped_categories} (frame, category) pair(s) were left empty and not scored"
        )
    held = [v for v in ev.view_info if v["heldout"]]
    if ev.train_views is not None:
        notes.append(
            f"{len(held)} of {len(ev.view_info)} labelled views were held out from field training "
            "(the others were training views)"
        )
    enc_spec = dict(engine.meta.get("encoder_spec") or {})
    description = (
        enc_spec.get("description")
        or getattr(encoder, "description", None)
        or (ev.bank.encoder_spec.get("description") if ev.bank is not None else None)
        or "unknown"
    )
    if enc_spec.get("name") == "captions":
        notes.append(
            "Teacher: ground-truth captions embedded by MiniLM (not CLIP). Relevancy at temperature "
            "10 saturates for related captions, and part queries score low even for the teacher; "
            "the protocol is not tuned to hide it."
        )
    labels_of_scales = list(engine.scale_labels)
    types, kinds, ap_pairs = ev.types, ev.kinds, ev.ap_pairs
    return EvalResult(
        scene=Path(ev.scene.root).name,
        run_dir=str(ev.run_dir),
        scene_dir=str(ev.scene.root),
        label_dir=str(ev.label_dir),
        bank_dir=ev.bank_path,
        encoder={
            "name": enc_spec.get("name", getattr(encoder, "name", None)),
            "description": description,
            "spec": enc_spec,
        },
        field={
            "variant": engine.variant,
            "dim": engine.dim,
            "step": engine.step,
            "num_scales": len(labels_of_scales),
            "scale_labels": labels_of_scales,
            # 2D views rendered deferred (the MLP per pixel) or per Gaussian (QueryConfig.render)
            "render": "deferred" if getattr(engine, "renders_deferred", False) else "gaussians",
            # composite's weights (query/composite.py): "unit", or "eq6" at a temperature ("uniform"
            # = infinity, 1 = the paper)
            "composite_weights": engine.config.composite_weights,
            "composite_temperature": temperature_name(engine.config.temperature),
        },
        modes=modes,
        boxes=boxes,
        scores=scores,
        split={m: {b: split_scores(s.pairs, types) for b, s in by.items()} for m, by in scores.items()},
        retrieval=(
            {
                m: {b: acc.summary(config.ks, config.retrieval_iou) for b, acc in by.items()}
                for m, by in ev.retrieval.items()
            }
            if ev.bank is not None
            else {}
        ),
        per_query={
            m: {b: _per_query(s.pairs, types, ap_pairs[m][b]) for b, s in by.items()} for m, by in scores.items()
        },
        query_types={c: types.get(c, "unknown") for c in ev.all_categories},
        query_types_source=ev.types_source,
        views=ev.view_info,
        relevancy_files=ev.relevancy_files,
        relevancy_mode=ev.npy_mode.name if ev.relevancy_dir is not None and ev.npy_mode is not None else None,
        ap={m: {b: ap_summary(v) for b, v in by.items()} for m, by in ap_pairs.items()},
        kinds={m: {b: kind_scores(s.pairs, ap_pairs[m][b], kinds) for b, s in by.items()} for m, by in scores.items()},
        query_kinds={c: kinds.get(c, "unknown") for c in ev.all_categories},
        query_kinds_source=ev.kinds_source,
        notes=notes,
        seconds=time.perf_counter() - t_start,
    )


def ap_summary(pairs: Sequence[Mapping]) -> dict:
    """mAP over pairs, how many used the exact mask, and the per-pair records."""
    return {
        "map": float(np.mean([p["ap"] for p in pairs])) if pairs else math.nan,
        "exact_masks": sum(p["mask"] == "exact" for p in pairs),
        "num_pairs": len(pairs),
        "pairs": list(pairs),
    }


def kind_scores(pairs: Sequence[PairRecord], ap_pairs: Sequence[Mapping], kinds: Mapping[str, str]) -> dict[str, dict]:
    """mIoU, localization accuracy and mAP per query kind (part / object / group / ...); kinds
    with no pair are listed with ``pairs: 0`` and NaN scores."""
    ap = {(p["frame"], p["query"]): p["ap"] for p in ap_pairs}
    out = {}
    for kind in QUERY_KINDS:
        sel = [p for p in pairs if kinds.get(p.category, "unknown") == kind]
        aps = [ap[(p.frame, p.category)] for p in sel if (p.frame, p.category) in ap]
        out[kind] = {
            "pairs": len(sel),
            "queries": sorted({p.category for p in sel}),
            "miou": float(np.mean([p.iou for p in sel])) if sel else math.nan,
            "loc_accuracy": float(np.mean([p.hit for p in sel])) if sel else math.nan,
            "map": float(np.mean(aps)) if aps else math.nan,
        }
    return out


# ------------------------------------------------------------------------------ comparison
def load_eval(path: Union[str, Path]) -> dict:
    """Read an ``eval.json`` written by ``n2f2 eval`` (for ``--compare``)."""
    path = Path(path)
    if path.is_dir():
        path = path / "eval.json"
    try:
        data = json.loads(path.read_text())
    except OSError as e:
        raise InputError(path, f"cannot read eval results ({e})") from None
    except json.JSONDecodeError as e:
        raise InputError(path, f"not valid JSON ({e.msg} at line {e.lineno})") from None
    if not isinstance(data, dict) or data.get("format") != "n2f2-eval-v1" or "per_query" not in data:
        raise InputError(path, "not an eval.json written by `n2f2 eval` (format n2f2-eval-v1)")
    return data


def compare_evals(reference: Mapping, current: Mapping, n: int = 3) -> dict[str, dict[str, Any]]:
    """Per-query IoU delta ``current - reference`` for every (mode, box) both evals scored
    (paper Table 8: top and bottom ``n``)."""
    out: dict[str, dict[str, Any]] = {}
    for m, by in current["per_query"].items():
        for b, queries in by.items():
            ref = reference["per_query"].get(m, {}).get(b)
            if ref is None:
                continue
            out.setdefault(m, {})[b] = query_deltas(
                {q: v["iou"] for q, v in ref.items()}, {q: v["iou"] for q, v in queries.items()}, n=n
            )
    return out
