"""Segments of one image as stacked non-overlapping id layers (:class:`SegmentSet`), and the mask
operations the segmenters and the segment bank share: packing masks into layers, LangSplat's
mask NMS vectorised (:func:`mask_nms`; theirs is a Python double loop over mask pairs), SAM's
greedy NMS and small-region clean-up, image checks and nearest-neighbour resizing.

A leaf: it imports no other module of :mod:`n2f2.segments`, so the segmenters (:mod:`.segmenters`
and the model-backed :mod:`.sam` and :mod:`.sam2` it registers) all import it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from ..errors import InputError


# ----------------------------------------------------------------------------- segment sets
@dataclass
class SegmentSet:
    """The segments of one image.

    ``layers`` are non-overlapping id maps; segment ``i`` is the pixels where
    ``layers[layer_of[i]] == i``. Optional per-segment ``captions`` (ground truth) and
    ``source_ids`` (e.g. ground-truth region ids) travel along.
    """

    layers: np.ndarray  # [L, H, W] int32, -1 = none
    scores: np.ndarray  # [S] float32 segmenter confidence (1 where it has none)
    captions: Optional[list[str]] = None  # [S]
    source_ids: Optional[np.ndarray] = None  # [S] int64

    def __post_init__(self) -> None:
        self.layers = np.asarray(self.layers, dtype=np.int32)
        if self.layers.ndim != 3:
            raise ValueError(f"segment layers must be [L, H, W], got shape {self.layers.shape}")
        self.scores = np.asarray(self.scores, dtype=np.float32).reshape(-1)
        if self.captions is not None and len(self.captions) != self.num_segments:
            raise ValueError("need one caption per segment")

    @property
    def num_segments(self) -> int:
        return int(self.scores.shape[0])

    @property
    def height(self) -> int:
        return int(self.layers.shape[1])

    @property
    def width(self) -> int:
        return int(self.layers.shape[2])

    def layer_of(self) -> np.ndarray:
        """[S] int64 layer index of each segment (-1 for a segment with no pixels)."""
        return segment_layers(self.layers, self.num_segments)

    def areas(self) -> np.ndarray:
        """[S] int64 pixel count of each segment."""
        return segment_areas(self.layers, self.num_segments)

    def masks(self, ids: Optional[Sequence[int]] = None) -> np.ndarray:
        """Boolean masks [len(ids), H, W] of the given segments (default: all)."""
        return layers_to_masks(self.layers, self.num_segments if ids is None else ids, layer_of=self.layer_of())

    @staticmethod
    def from_masks(
        masks: np.ndarray,  # [S, H, W] bool, may overlap
        scores: Optional[np.ndarray] = None,  # [S]
        captions: Optional[list[str]] = None,
    ) -> "SegmentSet":
        """Pack (possibly overlapping) masks into layers; segment i is ``masks[i]``."""
        masks = np.asarray(masks, dtype=bool)
        scores = np.ones(len(masks), np.float32) if scores is None else np.asarray(scores, np.float32)
        return SegmentSet(pack_layers(masks), scores, captions)

    @staticmethod
    def empty(height: int, width: int) -> "SegmentSet":
        return SegmentSet(np.full((0, height, width), -1, np.int32), np.zeros(0, np.float32))


def segment_areas(
    layers: np.ndarray,  # [L, H, W] int, -1 = none
    num_segments: int,
) -> np.ndarray:
    """[S] int64 pixel count per segment id (ids are unique across layers)."""
    ids = layers[layers >= 0]
    return np.bincount(ids.ravel(), minlength=num_segments)[:num_segments].astype(np.int64)


def segment_layers(
    layers: np.ndarray,  # [L, H, W] int, -1 = none
    num_segments: int,
) -> np.ndarray:
    """[S] int64 layer holding each segment, -1 for an empty segment. Raises ValueError when a
    segment id appears in two layers or exceeds ``num_segments``."""
    out = np.full(num_segments, -1, np.int64)
    for l, layer in enumerate(layers):
        ids = layer[layer >= 0]
        present = np.bincount(ids.ravel(), minlength=num_segments) > 0
        if present.size > num_segments:
            raise ValueError(f"segment id {int(ids.max())} in layer {l} exceeds the {num_segments} segments")
        clash = present & (out >= 0)
        if clash.any():
            raise ValueError(f"segment {int(np.flatnonzero(clash)[0])} appears in more than one layer")
        out[present] = l
    return out


def layers_to_masks(
    layers: np.ndarray,  # [L, H, W] int32
    ids,  # int S (all segments) or a sequence of segment ids
    layer_of: Optional[np.ndarray] = None,  # [S]
) -> np.ndarray:
    """Boolean masks [n, H, W] of segments ``ids`` (one vectorised comparison)."""
    if isinstance(ids, (int, np.integer)):
        ids = np.arange(int(ids))
    ids = np.asarray(ids, dtype=np.int64)
    if layer_of is None:
        layer_of = segment_layers(layers, int(ids.max()) + 1 if ids.size else 0)
    if ids.size == 0:
        return np.zeros((0,) + layers.shape[1:], dtype=bool)
    lay = np.maximum(layer_of[ids], 0)  # empty segments compare against layer 0 and match nothing
    return layers[lay] == np.where(layer_of[ids] >= 0, ids, -2)[:, None, None]


def pack_layers(masks: np.ndarray) -> np.ndarray:  # [S, H, W] bool -> [L, H, W] int32
    """Greedy packing of possibly-overlapping masks into non-overlapping id layers.

    Masks are placed largest first, each into the first layer where it overlaps nothing
    already there (so nested SAM masks - object, then its parts - end up on different layers).
    The loop is over masks, each step a vectorised test on the mask's own pixels."""
    masks = np.asarray(masks, dtype=bool)
    S, H, W = masks.shape
    flat = masks.reshape(S, -1)
    areas = flat.sum(axis=1)
    layers: list[np.ndarray] = []  # each [H * W] int32
    for i in np.argsort(-areas, kind="stable"):
        pix = np.flatnonzero(flat[i])
        for layer in layers:
            if (layer[pix] < 0).all():
                layer[pix] = i
                break
        else:
            layer = np.full(H * W, -1, np.int32)
            layer[pix] = i
            layers.append(layer)
    if not layers:
        return np.full((0, H, W), -1, np.int32)
    return np.stack(layers).reshape(len(layers), H, W)


def relabel_label_maps(
    label_maps: np.ndarray,  # [L, H, W] int, -1 = none, any ids
    min_area: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Turn per-level label maps (each already a partition) into bank layers with local ids
    0..S-1, numbered level by level. Labels with fewer than ``min_area`` pixels are dropped.

    Returns ``(layers [L, H, W] int32, source_ids [S] int64)`` where ``source_ids[i]`` is the
    original label of local segment i."""
    layers = np.full(label_maps.shape, -1, np.int32)
    sources = []
    offset = 0
    for l, lab in enumerate(label_maps):
        lab = np.asarray(lab, dtype=np.int64)
        if lab.size == 0:
            sources.append(np.zeros(0, np.int64))
            continue
        lo, hi = int(lab.min()), int(lab.max())
        if lo >= -1 and hi < 4 * lab.size + 1024:
            # Dense labels (Felzenszwalb, region ids): a lookup table, no sort.
            counts = np.bincount((lab + 1).ravel(), minlength=hi + 2)
            ids = np.arange(-1, hi + 1)
            keep = (ids >= 0) & (counts >= max(min_area, 1))
            local = np.full(ids.shape, -1, np.int64)
            local[keep] = offset + np.arange(int(keep.sum()))
            layers[l] = local[lab + 1]
        else:
            ids, inverse, counts = np.unique(lab, return_inverse=True, return_counts=True)
            keep = (ids >= 0) & (counts >= max(min_area, 1))
            local = np.full(ids.shape, -1, np.int64)
            local[keep] = offset + np.arange(int(keep.sum()))
            layers[l] = local[inverse.reshape(lab.shape)]
        sources.append(ids[keep].astype(np.int64))
        offset += int(keep.sum())
    return layers, (np.concatenate(sources) if sources else np.zeros(0, np.int64))


# ----------------------------------------------------------------------------- mask NMS
# Float32 values of flattened masks held at once while intersecting them (64 MB).
INTERSECT_BUDGET = 1 << 24


def mask_intersections(
    a: Tensor,  # [Sa, H, W] bool
    b: Tensor,  # [Sb, H, W] bool
) -> Tensor:  # [Sa, Sb] float64
    """Pixel counts of every pairwise intersection, as a matrix product of the flattened
    masks, accumulated over pixel chunks so that at most :data:`INTERSECT_BUDGET` float
    values exist at a time."""
    fa = a.reshape(a.shape[0], -1)
    fb = b.reshape(b.shape[0], -1)
    rows = fa.shape[0] + (0 if b is a else fb.shape[0])
    chunk = int(min(1 << 23, max(4096, INTERSECT_BUDGET // max(rows, 1))))
    inter = torch.zeros(fa.shape[0], fb.shape[0], dtype=torch.float64, device=a.device)
    for start in range(0, fa.shape[1], chunk):
        x = fa[:, start : start + chunk].float()
        y = x if b is a else fb[:, start : start + chunk].float()
        inter += (x @ y.T).double()  # counts per chunk <= chunk < 2^24: exact in float32
    return inter


def mask_areas(
    masks: Tensor,  # [S, H, W] bool
) -> Tensor:  # [S] float64
    """Pixel count of each mask, summed over pixel chunks (a sum over booleans converts its
    input to the sum's integer type: all at once, that is 4-8 bytes per pixel of every mask)."""
    flat = masks.reshape(masks.shape[0], -1)
    chunk = int(min(1 << 23, max(4096, INTERSECT_BUDGET // max(flat.shape[0], 1))))
    area = torch.zeros(flat.shape[0], dtype=torch.float64, device=masks.device)
    for start in range(0, flat.shape[1], chunk):
        area += flat[:, start : start + chunk].sum(1, dtype=torch.int32).double()
    return area


def mask_overlaps(
    masks: Tensor,  # [S, H, W] bool
) -> tuple[Tensor, Tensor]:
    """Pairwise intersections [S, S] and areas [S] (float64) of boolean masks."""
    inter = mask_intersections(masks, masks)
    return inter, torch.diagonal(inter).clone()


def mask_nms(
    masks: Tensor,  # [S, H, W] bool
    scores: Tensor,  # [S]
    iou_thr: float = 0.7,
    score_thr: float = 0.1,
    inner_thr: float = 0.2,
) -> Tensor:
    """LangSplat's mask NMS (``preprocess.py: mask_nms``), vectorised; returns kept indices
    [K] into ``masks``, in descending score order. Same defaults as LangSplat's function.

    Sort by score; a mask is dropped when (a) its IoU with a higher-scored mask exceeds
    ``iou_thr``, (b) its score is at most ``score_thr``, or (c) it lies mostly inside another
    mask (>= 85 % of it covered, while covering < 50 % of the other) and the product of the
    two coverage ratios is below ``inner_thr``. As in LangSplat, suppression is "fast NMS"
    (a suppressed mask still suppresses others), and if a criterion would drop every mask the
    three best-scored masks pass it.
    """
    S = int(scores.shape[0])
    if S == 0:
        return torch.zeros(0, dtype=torch.long, device=scores.device)
    scores_sorted, idx = torch.sort(scores, descending=True, stable=True)
    inter, area = mask_overlaps(masks[idx])
    union = area[:, None] + area[None, :] - inter
    iou = inter / union.clamp_min(1e-12)
    cover = inter / area[:, None].clamp_min(1e-12)  # cover[a, b]: fraction of a inside b
    cover_t = cover.T
    product = 1.0 - cover * cover_t
    upper = torch.ones(S, S, dtype=torch.bool, device=scores.device).triu(1)  # pairs i < j
    # LangSplat's loop over i < j writes [i, j] when j lies inside i, and [j, i] when i lies
    # inside j: element [a, b] is set exactly when b lies inside a.
    b_inside_a = (cover < 0.5) & (cover_t >= 0.85)
    inner = torch.where(b_inside_a & (upper | upper.T), product, torch.zeros_like(product))
    iou_max = torch.triu(iou, diagonal=1).max(dim=0).values
    inner_max_u = torch.triu(inner, diagonal=1).max(dim=0).values
    inner_max_l = torch.tril(inner, diagonal=1).max(dim=0).values  # diagonal=1 as in LangSplat

    def at_least_top3(keep: Tensor) -> Tensor:
        if not keep.any():
            keep = keep.clone()
            keep[: min(3, S)] = True  # scores are sorted: the first three are the top three
        return keep

    keep = iou_max <= iou_thr
    keep &= at_least_top3(scores_sorted > score_thr)
    keep &= at_least_top3(inner_max_u <= 1 - inner_thr)
    keep &= at_least_top3(inner_max_l <= 1 - inner_thr)
    return idx[keep]


def greedy_mask_nms(
    masks: Tensor,  # [S, H, W] bool
    scores: Tensor,  # [S]
    iou_thr: float = 0.7,
    settled: int = 0,
) -> Tensor:
    """Classic greedy NMS on mask IoU (SAM's ``box_nms_thresh`` step, on masks instead of
    boxes): returns kept indices [K] in descending score order. The loop runs over kept masks,
    each step one vectorised row of the IoU matrix.

    ``settled``: the first ``settled`` masks survived an earlier NMS together, so no two of them
    overlap by more than ``iou_thr`` and their pairs need no intersection; only pairs with a
    newer mask are measured (same result, a fraction of the work when few masks are new)."""
    S = int(scores.shape[0])
    if S == 0:
        return torch.zeros(0, dtype=torch.long, device=scores.device)
    order = torch.argsort(scores, descending=True, stable=True)
    settled = min(max(int(settled), 0), S)
    if settled == 0:
        inter, area = mask_overlaps(masks)
    else:
        area = mask_areas(masks)
        inter = torch.zeros(S, S, dtype=torch.float64, device=masks.device)
        if settled < S:
            new = mask_intersections(masks[settled:], masks)  # [S - settled, S]
            inter[settled:] = new
            inter[:, settled:] = new.T
    inter = inter[order][:, order]
    area = area[order]
    iou = (inter / (area[:, None] + area[None, :] - inter).clamp_min(1e-12)).cpu().numpy()
    suppressed = np.zeros(S, dtype=bool)
    keep = []
    for i in range(S):
        if suppressed[i]:
            continue
        keep.append(i)
        suppressed |= iou[i] > iou_thr
    return order[torch.as_tensor(keep, dtype=torch.long, device=order.device)]


def remove_small_regions(
    mask: np.ndarray,  # [H, W] bool
    min_area: int,
) -> np.ndarray:
    """SAM's ``min_mask_region_area`` post-processing: fill holes and remove islands smaller
    than ``min_area`` pixels (the largest island is kept if all are small)."""
    import cv2

    if min_area <= 0:
        return mask
    # Holes: small connected components of the background become foreground.
    n, labels, stats, _ = cv2.connectedComponentsWithStats((~mask).astype(np.uint8), connectivity=8)
    small = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] < min_area) + 1
    if small.size:
        mask = mask | np.isin(labels, small)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    sizes = stats[1:, cv2.CC_STAT_AREA]
    if sizes.size and (sizes < min_area).any():
        big = np.flatnonzero(sizes >= min_area) + 1
        if big.size == 0:
            big = np.array([int(np.argmax(sizes)) + 1])
        mask = np.isin(labels, big)
    return mask


# ----------------------------------------------------------------------------- helpers
def check_image(image: np.ndarray, path=None) -> np.ndarray:
    """Validate an image [H, W, 3] (float in [0, 1] or uint8); returns float32 [H, W, 3]."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise InputError(path, f"expected an RGB image [H, W, 3], got shape {image.shape}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise InputError(path, "image is empty (zero width or height)")
    if image.dtype == np.uint8:
        return image.astype(np.float32) / 255.0
    return image.astype(np.float32, copy=False)


def resize_nearest(
    labels: np.ndarray,  # [L, H0, W0] int
    height: int,
    width: int,
) -> np.ndarray:
    """Nearest-neighbour resize of label maps to [L, height, width], sampling at pixel centres
    (consistent with :mod:`n2f2.cameras`)."""
    L, H0, W0 = labels.shape
    if (H0, W0) == (height, width):
        return labels
    rows = np.minimum(((np.arange(height) + 0.5) * H0 / height).astype(np.int64), H0 - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * W0 / width).astype(np.int64), W0 - 1)
    return labels[:, rows[:, None], cols[None, :]]
