"""``n2f2 eval-hierarchy``: score a class-agnostic hierarchy of a scene's Gaussians (what
``n2f2 decompose RUN --out DECOMP`` writes) against a generated scene's ground-truth part /
object / group regions, beside a 2D-only baseline that sees each image alone.

It reads only what the evaluation needs of the decomposition (its file names and format from
:mod:`n2f2.hierarchy.files`), so a tree without embeddings can be scored:

* ``DECOMP/tree.json`` (``n2f2-tree-v1``): ``num_levels`` and ``nodes`` (global ``id``,
  ``parent`` (null at level 0, the coarsest), ``level``, ...);
* ``DECOMP/gaussian_nodes.npy``: int32 [N, L], the node of every Gaussian at every level;
* ``DECOMP/views/<image stem>/levels.npy``: int32 [L, H, W], coarsest level first, the node
  whose Gaussians contribute most to each pixel, -1 where none does.

The ground truth is a generated scene (``n2f2 demo``): ``SCENE/regions/<stem>.npy`` int32
[3, H, W] region ids per level (part, object, group; -1 none), ``SCENE/regions.json`` and the
images ``SCENE/images/<stem>.png``. Every view with a region map is a labelled view. Captures
without ground truth are scored against the segments the field was trained on instead
(``--segments BANK``, :class:`BankSegments`): every valid segment of every view is a region,
its kind the third of the field's scale ladder it was trained at (small, medium, large).

Metrics (IoU, consistency and shares are fractions in [0, 1] in the JSON; the Markdown report
shows them in percent):

* best IoU: each ground-truth region with at least ``min_pixels`` pixels in a view against
  every node at every level (a node's mask = the pixels whose id at the node's level is the
  node's id), the highest IoU kept; averaged over (view, region) pairs per kind and overall.
  A hierarchy that holds the scene's parts, objects and groups scores high at every kind.
* cross-view consistency: for a region seen in at least two views, the share of those views in
  which its best node is the one it matches most often; averaged over regions. 3D node ids are
  the same in every view, so a hierarchy of the scene (not of each image) scores high.
* nesting violations: the share of nodes below level 0 whose Gaussians are not all inside their
  parent's Gaussians (``tree.json`` + ``gaussian_nodes.npy``). A node that spans several levels
  unsplit (the same id in their columns) lies inside itself there.
* the 2D baseline: multi-scale Felzenszwalb (:class:`~n2f2.segments.segmenters.ClassicalSegmenter`)
  on each evaluated image, the same best IoU over all its segments at all scales. Its ids are
  per image, so its consistency is not defined (null).
"""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np

from ..config import option
from ..errors import InputError
from ..hierarchy.files import FORMAT as TREE_FORMAT
from ..hierarchy.files import LEVELS_NAME, NODES_NAME, TREE_NAME, view_folder
from ..validate import positive_float, positive_int

FORMAT = "n2f2-eval-hierarchy-v1"
JSON_NAME = "eval_hierarchy.json"
MD_NAME = "eval_hierarchy.md"
PLOT_NAME = "eval_hierarchy.png"
RESULT_NAMES = (JSON_NAME, MD_NAME, PLOT_NAME)
HIERARCHY = "3D hierarchy"
BASELINE = "2D baseline"
ALL = "all"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp")
SHOWN_IDS = 20  # violating node ids listed in the JSON

Log = Callable[[str], None]


@dataclass
class HierarchyEvalSettings:
    """What counts as a region seen in a view, and the 2D baseline's Felzenszwalb ladder."""

    min_pixels: int = option(
        100,
        help="a ground-truth region counts in a view when it covers at least this many pixels there",
        type=positive_int,
        metavar="PX",
    )
    baseline_scales: tuple[float, ...] = option(
        (25.0, 50.0, 100.0, 200.0, 400.0, 800.0, 1600.0),
        help="Felzenszwalb scales (k) of the 2D baseline, one partition each, fine to coarse",
        type=positive_float,
        nargs="+",
        metavar="K",
    )
    baseline_sigma: float = 0.8  # Gaussian pre-smoothing (as ClassicalSettings)
    baseline_min_size: int = 20  # Felzenszwalb's min_size (pixels)


@dataclass
class Match:
    """The best segment of one region in one view: its IoU, id and layer (the node's level for
    the hierarchy, the scale's index for the baseline); ``segment`` None when nothing overlaps.
    ``tied``: every segment with that same IoU, the best first (a part that is all of its
    object's visible pixels in a view matches both nodes equally)."""

    iou: float
    segment: Optional[int]
    layer: Optional[int]
    tied: list[int] = field(default_factory=list)


@dataclass
class GroundTruth:
    """A generated scene's region maps: the kinds (``regions.json`` levels), region entries by
    id, and the labelled views' stems (those with ``regions/<stem>.npy``). Each row of a region
    map holds the regions of one kind."""

    root: Path
    kinds: list[str]
    regions: dict[int, dict]
    stems: list[str]
    source: str = "labels"  # what the regions are: "labels" (ground truth) or "segments" (a bank)

    def region_map(self, stem: str) -> np.ndarray:  # [K, H, W] int32
        path = self.root / "regions" / f"{stem}.npy"
        ids = _load_npy(path, "ground-truth region map")
        if ids.ndim != 3 or ids.shape[0] != len(self.kinds) or not np.issubdtype(ids.dtype, np.integer):
            raise InputError(path, f"expected int region ids [{len(self.kinds)}, H, W], got {ids.dtype} {ids.shape}")
        return ids

    def kind_of(self, row: int, region: int) -> int:
        """The kind (index into ``kinds``) of ``region``, found in row ``row`` of a region map."""
        return row

    def image_dir(self) -> Path:
        return self.root / "images"

    def image_path(self, stem: str) -> Optional[Path]:
        for suffix in IMAGE_SUFFIXES:
            for name in (stem + suffix, stem + suffix.upper()):
                if (self.image_dir() / name).is_file():
                    return self.image_dir() / name
        return None


@dataclass
class BankSegments(GroundTruth):
    """The segments a field was trained on (a segment bank, ``n2f2 segments``) in place of ground
    truth, for captures without any: each valid segment is a region, of kind ``small``,
    ``medium`` or ``large`` by the third of the bank's quantised scale ``s`` in [0, 1) (the
    scale the field was trained on) it falls in. A region map's rows are the bank's layers (no
    two segments of a layer overlap); ids are made unique over the views, so cross-view
    consistency is not defined (no region is seen twice)."""

    offsets: dict[str, int] = field(default_factory=dict)  # stem -> id of its segment 0
    region_kinds: dict[int, int] = field(default_factory=dict)  # region id -> kind index
    images: Optional[Path] = None  # the bank's scene images, for the 2D baseline
    bank: Any = None  # the opened SegmentBank
    segmenter: str = ""  # the bank's segmenter ("classical" is the 2D baseline's Felzenszwalb)

    def region_map(self, stem: str) -> np.ndarray:  # [L, H, W] int64 global segment ids, -1 = none
        rec = self.bank.record(self.bank.index(stem))
        layers = np.asarray(rec.layers).astype(np.int64)
        keep = np.concatenate([np.asarray(rec.valid, bool), [False]])  # index -1 (none) maps to False
        return np.where(keep[layers], layers + self.offsets[stem], -1)

    def kind_of(self, row: int, region: int) -> int:
        return self.region_kinds[region]

    def image_dir(self) -> Path:
        return self.images if self.images is not None else self.root / "images"


SEGMENT_KINDS = ["small", "medium", "large"]  # thirds of a bank segment's quantised scale s


def read_bank_segments(path: Path) -> BankSegments:
    """A segment bank as :class:`BankSegments` (one line naming bank.json for a bank that cannot be read)."""
    from ..segments.bank import SegmentBank

    bank = SegmentBank.open(path)
    offsets, kinds, regions = {}, {}, {}
    next_id = 0
    for i, stem in enumerate(bank.image_names):
        rec = bank.record(i)
        offsets[stem] = next_id
        for s, q in enumerate(np.asarray(rec.quantized, dtype=np.float64)):
            if np.isfinite(q):
                kinds[next_id + s] = min(int(q * len(SEGMENT_KINDS)), len(SEGMENT_KINDS) - 1)
                regions[next_id + s] = {"name": f"{stem} segment {s}", "scale": float(q)}
        next_id += rec.num_segments
    source = bank.meta.get("source")
    images = Path(source) / "images" if isinstance(source, str) and (Path(source) / "images").is_dir() else None
    return BankSegments(
        Path(path),
        list(SEGMENT_KINDS),
        regions,
        list(bank.image_names),
        "segments",
        offsets,
        kinds,
        images,
        bank,
        str(bank.segmenter_spec.get("name", "")),
    )


# ----------------------------------------------------------------------------- readers
def _load_npy(path: Path, what: str) -> np.ndarray:
    """``np.load`` without pickles; a file that cannot be read is one InputError line."""
    if not path.is_file():
        raise InputError(path, f"no {what} here")
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as e:
        raise InputError(path, f"cannot read the {what} ({type(e).__name__}: {e})") from None


def _load_json(path: Path, what: str) -> dict:
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError, UnicodeDecodeError) as e:
        raise InputError(path, f"cannot read the {what} ({type(e).__name__})") from None
    if not isinstance(data, dict):
        raise InputError(path, f"the {what} is not a JSON object")
    return data


def read_tree(decomp: Path, run_dir: Path) -> dict:
    """``DECOMP/tree.json``, checked: the format, ``num_levels`` >= 1, and nodes with int ids
    and levels in range. Missing: one line saying how to make it."""
    path = decomp / TREE_NAME
    if not path.is_file():
        raise InputError(decomp, f"no tree.json here: run `n2f2 decompose {run_dir} --out {decomp}` first")
    tree = _load_json(path, "hierarchy tree")
    if tree.get("format") != TREE_FORMAT:
        raise InputError(path, f"not an {TREE_FORMAT} tree (format {tree.get('format')!r})")
    L, nodes = tree.get("num_levels"), tree.get("nodes")
    if not isinstance(L, int) or L < 1 or not isinstance(nodes, list):
        raise InputError(path, "needs num_levels (an integer >= 1) and a list of nodes")
    for node in nodes:
        ok = isinstance(node, dict) and isinstance(node.get("id"), int) and isinstance(node.get("level"), int)
        if not ok or not 0 <= node["level"] < L:
            raise InputError(path, f"bad node (an int id and a level in [0, {L}) needed): {str(node)[:80]}")
    return tree


def read_gaussian_nodes(decomp: Path, num_levels: int) -> np.ndarray:  # [N, L] int
    """``DECOMP/gaussian_nodes.npy``: integer ids [N, num_levels]."""
    path = decomp / NODES_NAME
    ids = _load_npy(path, "node ids of the Gaussians")
    if ids.ndim != 2 or ids.shape[1] != num_levels or not np.issubdtype(ids.dtype, np.integer):
        raise InputError(path, f"expected int node ids [N, {num_levels}], got {ids.dtype} {ids.shape}")
    return ids


def read_view_levels(decomp: Path, stem: str, num_levels: int) -> np.ndarray:  # [L, H, W] int
    """``DECOMP/views/<stem>/levels.npy``: integer node ids [num_levels, H, W]."""
    path = view_folder(decomp, stem) / LEVELS_NAME
    ids = _load_npy(path, "node ids of the view")
    if ids.ndim != 3 or ids.shape[0] != num_levels or not np.issubdtype(ids.dtype, np.integer):
        raise InputError(path, f"expected int node ids [{num_levels}, H, W], got {ids.dtype} {ids.shape}")
    return ids


def read_ground_truth(scene: Path) -> GroundTruth:
    """The generated scene's ``regions.json`` and the stems of ``regions/*.npy``; a folder
    without them is refused in one line."""
    if not (scene / "regions").is_dir() or not (scene / "regions.json").is_file():
        raise InputError(
            scene, "no ground-truth regions (regions/ and regions.json, as `n2f2 demo` writes in OUT/scene)"
        )
    data = _load_json(scene / "regions.json", "region list")
    kinds = data.get("levels", ["part", "object", "group"])
    entries = data.get("regions", [])
    if not isinstance(kinds, list) or not isinstance(entries, list):
        raise InputError(scene / "regions.json", "needs a list of levels and a list of regions")
    regions = {int(r["id"]): r for r in entries if isinstance(r, dict) and isinstance(r.get("id"), int)}
    stems = sorted(p.stem for p in (scene / "regions").glob("*.npy") if not p.name.startswith("."))
    if not stems:
        raise InputError(scene / "regions", "no region maps (<image stem>.npy) here")
    return GroundTruth(scene, [str(k) for k in kinds], regions, stems)


def read_image(path: Path, height: int, width: int) -> tuple[np.ndarray, Optional[tuple[int, int]]]:
    """An RGB image [H, W, 3] uint8 at ``height`` x ``width`` (resized as scenes load their
    images, :func:`n2f2.data.scene.load_image`); with its original (width, height) when it was
    resized, else None."""
    from ..data.scene import load_image, open_image

    with open_image(path) as im:
        size = tuple(im.size)
    rgb = load_image(path, width, height)  # float32 [H, W, 3] in [0, 1]
    return np.round(rgb * 255.0).astype(np.uint8), (size if size != (width, height) else None)


# ----------------------------------------------------------------------------- metrics
def _overlaps(
    region_index: np.ndarray,  # [P] int index into the region ids of each pixel
    region_area: np.ndarray,  # [R] pixels of each region
    segments: np.ndarray,  # [P] int segment id of each pixel, -1 = none
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # ([Q] region index, [Q] segment id, [Q] IoU)
    """The IoU of every overlapping (region, segment) pair of one layer, ordered by region and
    then segment id; pairs that do not overlap have IoU 0 and are left out."""
    seg_ids, seg_index, seg_area = np.unique(segments, return_inverse=True, return_counts=True)
    seg_index = seg_index.reshape(-1)
    has = seg_ids[seg_index] >= 0
    key = region_index[has].astype(np.int64) * len(seg_ids) + seg_index[has]
    keys, inter = np.unique(key, return_counts=True)
    ri, si = np.divmod(keys, len(seg_ids))
    return ri, seg_ids[si].astype(np.int64), inter / (region_area[ri] + seg_area[si] - inter)


def best_matches(
    regions: np.ndarray,  # [K, H, W] int region ids per ground-truth level, -1 = none
    layers: np.ndarray,  # [L, H, W] int segment ids per layer, -1 = none
    min_pixels: int,
) -> dict[tuple[int, int], tuple[int, Match]]:
    """``(kind index, region id) -> (pixels, best match)`` for every region with at least
    ``min_pixels`` pixels: the highest IoU with any segment of any layer (a segment's mask is
    where its layer holds its id). Ties go to the earlier layer (the coarser level), then the
    smaller id; all of them are kept in ``Match.tied``."""
    found = {}
    for k in range(regions.shape[0]):
        ids, index, area = np.unique(regions[k], return_inverse=True, return_counts=True)
        big = np.flatnonzero((ids >= 0) & (area >= min_pixels))
        if not len(big):
            continue
        pairs = [_overlaps(index.reshape(-1), area, layer.reshape(-1)) for layer in layers]
        ri, seg, iou = (np.concatenate([p[j] for p in pairs]) for j in range(3))  # layer by layer
        layer_of = np.concatenate([np.full(len(p[0]), n) for n, p in enumerate(pairs)])
        best = np.zeros(len(ids))
        np.maximum.at(best, ri, iou)
        winners = np.flatnonzero((iou == best[ri]) & (iou > 0))
        winners = winners[np.argsort(ri[winners], kind="stable")]  # per region, in (layer, id) order
        split = np.split(winners, np.flatnonzero(np.diff(ri[winners])) + 1) if len(winners) else []
        by_region = {int(ri[w[0]]): w for w in split}
        for i in big:
            w = by_region.get(int(i))
            match = Match(0.0, None, None)
            if w is not None:
                tied = list(dict.fromkeys(int(x) for x in seg[w]))
                match = Match(float(best[i]), int(seg[w[0]]), int(layer_of[w[0]]), tied)
            found[(k, int(ids[i]))] = (int(area[i]), match)
    return found


def consistency(
    best_nodes: dict[tuple[int, int], list[list[int]]],  # (kind, region) -> per view: its tied best nodes
    kinds: list[str],
) -> dict:
    """Cross-view consistency of the best nodes: for each region seen in at least two views,
    the share of its views whose best node is its most frequent best node. A view whose best
    IoU is tied between nodes counts each of them (so a tie never breaks consistency); a view
    where no node overlaps never matches. The mean over regions, overall and per kind, and each
    region's numbers."""
    per_region = []
    for (k, rid), views in best_nodes.items():
        if len(views) < 2:
            continue
        counts = Counter(n for nodes in views for n in nodes)
        mode = counts.most_common(1)[0][0] if counts else None  # equal counts: the first seen
        hits = sum(mode in nodes for nodes in views)
        per_region.append(
            {"kind": kinds[k], "region": rid, "views": len(views), "mode_node": mode, "share": hits / len(views)}
        )

    def mean(rows: list[dict]) -> dict:
        return {"regions": len(rows), "mean": float(np.mean([r["share"] for r in rows])) if rows else None}

    return {
        **mean(per_region),
        "per_kind": {kind: mean([r for r in per_region if r["kind"] == kind]) for kind in kinds},
        "per_region": per_region,
    }


def nesting_violations(
    tree: dict,
    gaussian_nodes: np.ndarray,  # [N, L] int node id of every Gaussian per level, -1 = none
) -> dict:
    """The nodes below level 0 that do not nest: a node whose Gaussians are not all in its
    parent's (their id one level up is not the node's parent), or that has no parent. A node
    without Gaussians nests trivially (counted as empty)."""
    parents_seen: dict[int, set[int]] = {}
    for level in range(1, gaussian_nodes.shape[1]):
        pairs = np.unique(gaussian_nodes[:, level - 1 : level + 1], axis=0)  # [P, 2] (parent, child)
        for up, node in pairs.tolist():
            if node >= 0 and up != node:  # a node spanning both levels is inside itself
                parents_seen.setdefault(node, set()).add(up)
    checked, empty, bad = 0, 0, []
    for node in tree["nodes"]:
        if node["level"] < 1:
            continue
        checked += 1
        seen = parents_seen.get(node["id"], set())
        empty += not seen
        if node.get("parent") is None or seen - {node["parent"]}:
            bad.append(node["id"])
    return {
        "nodes": checked,
        "violations": len(bad),
        "share": len(bad) / checked if checked else None,
        "empty_nodes": empty,
        "violating_nodes": sorted(bad)[:SHOWN_IDS],
    }


def kind_means(records: list[dict], kinds: list[str], key: str) -> dict:
    """Mean of ``records[i][key]`` (the best IoUs; None = not scored) per kind and over all:
    ``{kind: {"regions": n, "mean_best_iou": x | None}}`` plus ``"all"``."""

    def mean(rows: list[dict]) -> dict:
        values = [r[key] for r in rows if r[key] is not None]
        return {"regions": len(values), "mean_best_iou": float(np.mean(values)) if values else None}

    return {**{k: mean([r for r in records if r["kind"] == k]) for k in kinds}, ALL: mean(records)}


# ----------------------------------------------------------------------------- one view
def baseline_layers(
    image: np.ndarray,  # [H, W, 3] uint8
    settings: HierarchyEvalSettings,
) -> np.ndarray:  # [S, H, W] int32 segment ids, one layer per scale
    """The 2D-only baseline: Felzenszwalb at each scale of the ladder, through the classical
    segmenter (same call and settings class as the segment bank's ``classical``)."""
    from ..segments.segmenters import ClassicalSegmenter, ClassicalSettings

    st = ClassicalSettings(
        scales=tuple(settings.baseline_scales), sigma=settings.baseline_sigma, min_area=settings.baseline_min_size
    )
    return ClassicalSegmenter(st)(image).layers


def evaluate_view(
    gt: GroundTruth,
    stem: str,
    levels: np.ndarray,  # [L, H, W] int node ids of the view
    settings: HierarchyEvalSettings,
    notes: Counter,
) -> list[dict]:
    """One view's records: each ground-truth region seen (>= ``min_pixels``) with its best IoU
    and node in the hierarchy and its best IoU and segment in the 2D baseline (None without an
    image). Region maps of another size are resized (nearest) to the levels', images likewise."""
    from ..segments.masks import resize_nearest

    H, W = levels.shape[1:]
    regions = gt.region_map(stem)
    if regions.shape[1:] != (H, W):
        notes[f"ground-truth regions resized (nearest) from {regions.shape[2]}x{regions.shape[1]} to {W}x{H}"] += 1
        regions = resize_nearest(regions, H, W)
    found = best_matches(regions, levels, settings.min_pixels)
    baseline: dict = {}
    image_path = gt.image_path(stem)
    if image_path is None:
        notes["no image for the 2D baseline (view left out of its means)"] += 1
    else:
        image, resized = read_image(image_path, H, W)
        if resized is not None:
            notes[f"images resized (bilinear) from {resized[0]}x{resized[1]} to {W}x{H} for the 2D baseline"] += 1
        baseline = best_matches(regions, baseline_layers(image, settings), settings.min_pixels)
    records = []
    for (k, rid), (pixels, match) in found.items():
        base = baseline.get((k, rid), (0, None))[1]
        scale = None if base is None or base.layer is None else settings.baseline_scales[base.layer]
        entry = gt.regions.get(rid, {})
        records.append(
            {
                "kind": gt.kinds[gt.kind_of(k, rid)],
                "region": rid,
                "name": entry.get("name"),
                "pixels": pixels,
                "best_iou": match.iou,
                "best_node": match.segment,
                "best_level": match.layer,
                "tied_nodes": match.tied[1:],
                "baseline_best_iou": None if base is None else base.iou,
                "baseline_best_scale": scale,
                "baseline_best_segment": None if base is None else base.segment,
            }
        )
    return records


# ----------------------------------------------------------------------------- the evaluation
@dataclass
class HierarchyInputs:
    """The checked inputs: the tree, the Gaussians' node ids, the ground truth, and which
    labelled views have levels (``views``) and which do not (``skipped``)."""

    run_dir: Path
    decomp: Path
    tree: dict
    gaussian_nodes: np.ndarray  # [N, L] int
    gt: GroundTruth
    views: list[str]
    skipped: list[str] = field(default_factory=list)


def check_inputs(
    run_dir: Path, decomp: Path, labels: Optional[Path], segments: Optional[Path] = None
) -> HierarchyInputs:
    """Read and check everything before any output is claimed; each refusal is one line. The
    regions are the generated scene ``labels``' ground truth, or the segment bank ``segments``."""
    if (labels is None) == (segments is None):
        raise InputError(None, "give either the ground truth (--labels SCENE) or a segment bank (--segments BANK)")
    if not run_dir.is_dir():
        raise InputError(run_dir, "not a run folder")
    tree = read_tree(decomp, run_dir)
    nodes = read_gaussian_nodes(decomp, tree["num_levels"])
    gt = read_ground_truth(labels) if labels is not None else read_bank_segments(Path(str(segments)))
    views = [s for s in gt.stems if (view_folder(decomp, s) / LEVELS_NAME).is_file()]
    if not views:
        raise InputError(
            decomp / "views",
            f"none of the {len(gt.stems)} labelled views of {gt.root} has views/<stem>/levels.npy; "
            f"run `n2f2 decompose {run_dir} --out {decomp} --views all`",
        )
    return HierarchyInputs(run_dir, decomp, tree, nodes, gt, views, [s for s in gt.stems if s not in views])


def hierarchy_result(inputs: HierarchyInputs, settings: HierarchyEvalSettings) -> dict:
    """Every number of the evaluation (the JSON written as ``eval_hierarchy.json``)."""
    gt, notes = inputs.gt, Counter()
    per_view, records = {}, []
    best_nodes: dict[tuple[int, int], list[list[int]]] = {}
    for stem in inputs.views:
        levels = read_view_levels(inputs.decomp, stem, inputs.tree["num_levels"])
        view = evaluate_view(gt, stem, levels, settings, notes)
        per_view[stem] = {"size": [int(levels.shape[1]), int(levels.shape[2])], "regions": view}
        records += view
        for r in view:
            best_nodes.setdefault((gt.kinds.index(r["kind"]), r["region"]), []).append(
                [] if r["best_node"] is None else [r["best_node"], *r["tied_nodes"]]
            )
    hierarchy, baseline = kind_means(records, gt.kinds, "best_iou"), kind_means(records, gt.kinds, "baseline_best_iou")
    levels_info = inputs.tree.get("levels", [])
    return {
        "format": FORMAT,
        "run": str(inputs.run_dir),
        "decomposition": str(inputs.decomp),
        "labels": str(gt.root),
        "regions": gt.source,  # "labels": ground truth; "segments": the segment bank's segments
        "units": "best IoU, consistency and shares are fractions in [0, 1]",
        "settings": {**asdict(settings), "baseline_scales": list(settings.baseline_scales)},
        "kinds": gt.kinds,
        # labelled: the views with a ground-truth region map; skipped: those without levels.npy
        "views": {"labelled": len(gt.stems), "evaluated": inputs.views, "skipped": inputs.skipped},
        "hierarchy": {
            "num_levels": inputs.tree["num_levels"],
            "levels": levels_info if isinstance(levels_info, list) else [],
            "best_iou": hierarchy,
            "consistency": consistency(best_nodes, gt.kinds),
            "nesting": nesting_violations(inputs.tree, inputs.gaussian_nodes),
        },
        "baseline": {
            "method": "multi-scale Felzenszwalb (skimage.segmentation.felzenszwalb), best segment over all scales",
            "best_iou": baseline,
            "consistency": None,
        },
        "plot": {
            "file": PLOT_NAME,
            "values": {
                series: {k: v["mean_best_iou"] for k, v in means.items() if k != ALL}
                for series, means in ((HIERARCHY, hierarchy), (BASELINE, baseline))
            },
        },
        "per_view": per_view,
        "notes": [f"{text} in {n} view{'s' * (n != 1)}" for text, n in notes.items()]
        + ([f"{len(inputs.skipped)} labelled views without levels.npy skipped"] if inputs.skipped else [])
        + (
            [
                "the bank's segments come from the classical segmenter, the 2D baseline's own Felzenszwalb: "
                "the baseline matches them by construction"
            ]
            if isinstance(gt, BankSegments) and gt.segmenter == "classical"
            else []
        ),
    }


# ----------------------------------------------------------------------------- reports
def markdown_report(result: dict) -> str:
    """``eval_hierarchy.md``: the per-kind table, then consistency, nesting, levels and notes."""
    from .tables import fmt, markdown_table, pct

    h, b = result["hierarchy"], result["baseline"]
    rows = [
        [
            k,
            fmt(h["best_iou"][k]["regions"]),
            pct(h["best_iou"][k]["mean_best_iou"]),
            pct(b["best_iou"][k]["mean_best_iou"]),
        ]
        for k in [*result["kinds"], ALL]
    ]
    c, n = h["consistency"], h["nesting"]
    scales = ", ".join(f"{s:g}" for s in result["settings"]["baseline_scales"])
    level_names = ", ".join(str(lv.get("scale_label", lv.get("level"))) for lv in h["levels"] if isinstance(lv, dict))
    bank = result.get("regions") == "segments"
    against = "the segments of the segment bank" if bank else "the ground truth of"
    region = "segment of the bank" if bank else "ground-truth region"
    lines = [
        "# Hierarchy evaluation",
        "",
        f"Decomposition `{result['decomposition']}` of run `{result['run']}` against {against} "
        f"`{result['labels']}`: {len(result['views']['evaluated'])} of {result['views']['labelled']} labelled views.",
        "",
        *(
            [
                "The bank's segments are what the field was trained on, not ground truth; kinds are the thirds "
                "of their quantised scale s (small < 1/3 <= medium < 2/3 <= large).",
                "",
            ]
            if bank
            else []
        ),
        f"Best IoU (%) of each {region} with at least {result['settings']['min_pixels']} pixels in a view: "
        "with any node at any level of the 3D hierarchy, and with any segment of the 2D baseline "
        f"(Felzenszwalb at scales {scales}); mean over (view, region) pairs.",
        "",
        markdown_table(["kind", "regions", f"mean best IoU {HIERARCHY}", f"mean best IoU {BASELINE}"], rows),
        f"- cross-view consistency ({HIERARCHY}): {pct(c['mean'])} % over {c['regions']} regions seen in >= 2 views "
        f"({BASELINE}: not defined, its segment ids are per image)",
        f"- nesting violations: {pct(n['share'])} % of {n['nodes']} nodes below level 0 ({n['violations']} nodes)",
        f"- levels: {h['num_levels']}" + (f" ({level_names})" if level_names else ""),
    ]
    if result["notes"]:
        lines += ["", "## Notes", "", *[f"- {note}" for note in result["notes"]]]
    return "\n".join(lines) + "\n"


def summary_line(result: dict, out: Path) -> str:
    """The one line printed at the end."""
    from .tables import pct

    h = result["hierarchy"]

    def iou(series: str, kind: str) -> str:
        return pct(result[series]["best_iou"][kind]["mean_best_iou"])

    per_kind = ", ".join(f"{k} {iou('hierarchy', k)}/{iou('baseline', k)}" for k in result["kinds"])
    return (
        f"eval-hierarchy: {len(result['views']['evaluated'])} views, {h['best_iou'][ALL]['regions']} regions: "
        f"mean best IoU 3D {iou('hierarchy', ALL)}% vs 2D {iou('baseline', ALL)}% (3D/2D: {per_kind}); "
        f"consistency {pct(h['consistency']['mean'])}%; nesting violations {pct(h['nesting']['share'])}% of "
        f"{h['nesting']['nodes']} nodes; {h['num_levels']} levels -> {out}"
    )


def write_reports(out: Path, result: dict) -> None:
    """The JSON, the Markdown report and the bar chart of the per-kind means."""
    from ..io import write_json, write_text
    from .reports import plot_grouped_bars

    values = {s: {k: v for k, v in per.items() if v is not None} for s, per in result["plot"]["values"].items()}
    plot_grouped_bars(out / PLOT_NAME, values, title="mean best IoU per kind", ylabel="mean best IoU %")
    write_text(out / MD_NAME, markdown_report(result))
    write_json(out / JSON_NAME, result)


def evaluate_hierarchy(
    run_dir: str | Path,
    decomp: str | Path,
    labels: str | Path | None = None,
    *,
    segments: str | Path | None = None,
    out: str | Path | None = None,
    settings: Optional[HierarchyEvalSettings] = None,
    force: bool = False,
    log: Log = print,
) -> dict:
    """Score the decomposition ``decomp`` of ``run_dir`` against the ground truth of the generated
    scene ``labels``, or against the segment bank ``segments`` the field was trained on
    (:class:`BankSegments`), into ``out`` (default ``DECOMP/eval_hierarchy``); returns the JSON's
    dict. Inputs are checked before the output folder is claimed, and earlier results are only
    replaced with ``force``."""
    from ..io import claim_out_dir, remove_results

    settings = settings or HierarchyEvalSettings()
    inputs = check_inputs(
        Path(run_dir),
        Path(decomp),
        None if labels is None else Path(labels),
        None if segments is None else Path(segments),
    )
    out = Path(out) if out is not None else Path(decomp) / "eval_hierarchy"
    present = claim_out_dir(out, RESULT_NAMES, force=force, resume_flag=None)
    result = hierarchy_result(inputs, settings)
    remove_results(out, present)
    write_reports(out, result)
    log(summary_line(result, out))
    return result
