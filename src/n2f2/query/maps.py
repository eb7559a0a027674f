"""LangSplat's post-processing of relevancy maps: mean filter, the segmentation map and its
threshold, the majority filter, and the maxima used for localisation.

These are the rules of LangSplat's ``eval/evaluate_iou_loc.py`` and ``eval/utils.py``, written
once: ``n2f2 query`` and the viewer use them to turn relevancy into masks and locations, and
:mod:`n2f2.eval.protocol` (which documents each rule against LangSplat's code) scores with them.

Localisation, one rule for every caller (:func:`localization_maxima`): the maxima of ``box(R)``,
the mean-filtered raw relevancy (no 0.5 mix). A point is an integer pixel index ``(x, y)`` =
(column, row) of the map as rendered, in its own ``H x W``; the pixel's centre lies at image
coordinates ``(x + 0.5, y + 0.5)`` (n2f2's camera convention). Nothing rescales a point: the
viewer renders a training view at the size ``n2f2 query`` does (same run, same ``--full-res``),
so their points compare as they are; a map rendered at another size has its own pixels (scale
by the ratio of the widths and heights to compare). ``n2f2 query`` (``localization`` in
query.json), the viewer's ``/api/query`` and its 3D "Render view" report :func:`localization_point`,
the first maximum in row-major order; the evaluation scores a hit when any maximum lies in a label
box, whose corners are in the same pixel coordinates (LangSplat compares these integers with them).

Flat maps (:func:`flat_warning`): a map whose range over the view is below :data:`FLAT_RANGE`
carries no signal; its mask and point are artefacts of min-max normalisation and ties, and the
outputs say so.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from functools import lru_cache
from typing import Callable, Literal, Optional, Union

import numpy as np

# LangSplat constants (eval/evaluate_iou_loc.py, eval/openclip_encoder.py).
LANGSPLAT_BOX_SIZE = 30  # mean-filter size, pixels
LANGSPLAT_THRESHOLD = 0.4  # --mask_thresh default
LANGSPLAT_MIX = 0.5  # R' = 0.5 * (box(R) + R) for segmentation
LANGSPLAT_MAJORITY_RADIUS = 3  # utils.smooth: scale = 3
# Width of the LERF-OVS label images LangSplat evaluates at (about 986 px, e.g. 986 x 728).
# Reference width for box_size="scaled"; pass box_ref_width to use another.
LERF_REFERENCE_WIDTH = 986

# A relevancy map whose range (max - min) over the view is below this is flat: it carries no
# signal. Relevancy is a softmax pair probability, sigmoid(10 (cos_t - max_c cos_c)) in (0, 1),
# whose slope is at most 2.5 per unit of cosine: a range of 1e-3 is a cosine margin under 4e-4
# across the whole view, far below any difference a threshold could act on (the protocol's 0.4
# acts after min-max normalisation, which stretches any range, float32 rounding included, to
# [0, 1]), and far above the float32 rounding of a map of equal features (0 to a few 1e-6, e.g.
# 0.4999987-0.5000009). Even the tests' tiny 80-iteration field gives maps spanning about 0.07.
FLAT_RANGE = 1e-3

BoxSize = Union[int, Literal["scaled"]]
Radius = Union[int, Literal["scaled"]]


def resolve_box_size(box_size: BoxSize, width: int, ref_width: int = LERF_REFERENCE_WIDTH) -> int:
    """The filter size in pixels: ``box_size`` itself, or for ``"scaled"``
    ``round(30 * width / ref_width)`` (halves round up), at least 1."""
    if box_size == "scaled":
        return max(1, int(math.floor(LANGSPLAT_BOX_SIZE * width / ref_width + 0.5)))
    if not isinstance(box_size, (int, np.integer)) or box_size < 1:
        raise ValueError(f"box_size must be a positive int or 'scaled', got {box_size!r}")
    return int(box_size)


def resolve_majority_radius(radius: Radius, width: int, ref_width: int = LERF_REFERENCE_WIDTH) -> int:
    """The majority half-window: ``radius`` itself, or for ``"scaled"``
    ``round(3 * width / ref_width)`` (halves round up), at least 0."""
    if radius == "scaled":
        return max(0, int(math.floor(LANGSPLAT_MAJORITY_RADIUS * width / ref_width + 0.5)))
    if not isinstance(radius, (int, np.integer)) or radius < 0:
        raise ValueError(f"majority radius must be an int >= 0 or 'scaled', got {radius!r}")
    return int(radius)


# ------------------------------------------------------------------------------ filters
MIN_MAPS_PER_THREAD = 8  # a stack filters on one thread below 2x this many maps
# OpenCV's filter2D filters through the DFT from an 11x11 kernel up (0.5 ms per 160x120 map at
# 30x30); below, a map costs about what handing it to a thread does.
THREADED_FROM_SIZE = 11


@lru_cache(maxsize=None)
def _executor(threads: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=threads, thread_name_prefix="n2f2-maps")


def _each_map(
    fn: Callable[[np.ndarray], np.ndarray],
    stack: np.ndarray,  # [n, H, W]
    out: np.ndarray,  # [n, H, W] written: out[i] = fn(stack[i])
    threaded: bool,
) -> None:
    """Apply an OpenCV filter map by map; ``threaded``: the stack split into contiguous chunks
    over torch's thread count (OpenCV releases the GIL). The same call on the same map whatever
    the split, so the result is bitwise one loop's."""
    import torch

    n = len(stack)
    threads = min(torch.get_num_threads(), n // MIN_MAPS_PER_THREAD) if threaded else 1

    def run(lo: int, hi: int) -> None:
        for i in range(lo, hi):
            out[i] = fn(stack[i])

    if threads < 2:
        run(0, n)
        return
    bounds = np.linspace(0, n, threads + 1).round().astype(int)
    for job in [_executor(threads).submit(run, int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]:
        job.result()


def box_filter(
    relevancy: np.ndarray,  # [H, W] or [..., H, W] relevancy maps
    size: int = LANGSPLAT_BOX_SIZE,
) -> np.ndarray:  # float32, same shape
    """``size x size`` mean filter exactly as LangSplat computes it: ``cv2.filter2D`` on a
    float32 map with kernel ``np.ones((size, size)) / size**2``, default anchor (kernel centre)
    and default border (BORDER_REFLECT_101); a stack ``[..., H, W]`` map by map."""
    import cv2

    r = np.asarray(relevancy, dtype=np.float32)
    if r.ndim < 2 or r.shape[-1] < 1 or r.shape[-2] < 1:
        raise ValueError(f"relevancy must be [..., H, W] with H, W >= 1, got shape {r.shape}")
    size = int(size)
    if size < 1:
        raise ValueError(f"box size must be >= 1, got {size}")
    kernel = np.ones((size, size)) / (size**2)  # float64, as in LangSplat
    h, w = r.shape[-2:]
    if r.ndim == 2:
        return cv2.filter2D(np.ascontiguousarray(r), -1, kernel)
    # Map by map: bitwise what one multi-channel call gives (LangSplat's localization filters its
    # [H, W, levels] stack in one call), and faster on CPU than the transposes that call needs.
    flat = r.reshape(-1, h, w)
    out = np.empty_like(flat)
    _each_map(lambda one: cv2.filter2D(np.ascontiguousarray(one), -1, kernel), flat, out, size >= THREADED_FROM_SIZE)
    return out.reshape(r.shape)


def smoothed_relevancy(
    relevancy: np.ndarray,  # [..., H, W]
    size: int = LANGSPLAT_BOX_SIZE,
) -> np.ndarray:  # float32 [..., H, W]
    """LangSplat's segmentation map ``R' = 0.5 * (box(R) + R)`` (float32 arithmetic)."""
    r = np.asarray(relevancy, dtype=np.float32)
    return np.float32(LANGSPLAT_MIX) * (box_filter(r, size) + r)


def normalized_for_threshold(
    smoothed: np.ndarray,  # [...] one map (any shape: an image, or per-Gaussian scores)
    stack: bool = False,  # True: ``smoothed`` is [..., H, W], each [H, W] map normalised alone
) -> np.ndarray:  # float32, same shape
    """LangSplat's map before thresholding: subtract the minimum, divide by (max + 1e-9), map
    [0, 1] to [-1, 1] and clip to [0, 1]. Computed in float32 in LangSplat's order (a stack
    gives bitwise the same maps as one map at a time)."""
    out = np.asarray(smoothed, dtype=np.float32)
    axes = (-2, -1) if stack else None
    out = out - out.min(axis=axes, keepdims=stack)
    out = out / (out.max(axis=axes, keepdims=stack) + np.float32(1e-9))
    out = out * np.float32(2.0) + np.float32(-1.0)
    return np.clip(out, np.float32(0.0), np.float32(1.0))


def majority_filter(
    mask: np.ndarray,  # [..., H, W] binary (bool or 0/1); a stack is filtered map by map
    radius: int = LANGSPLAT_MAJORITY_RADIUS,
) -> np.ndarray:  # uint8 [..., H, W], 0/1
    """LangSplat's ``utils.smooth``, as window counts of an unnormalised box filter.

    Pixel (i, j) becomes the majority value of the window rows
    ``[max(0, i - r), min(i + r + 1, H - 1))`` x cols ``[max(0, j - r), min(j + r + 1, W - 1))``.
    Kept from LangSplat: the upper bound is ``H - 1`` / ``W - 1``, so the last row and column
    never take part in any window (an off-by-one at the far edge), and a tie goes to 0
    (``argmax(bincount)`` returns the first maximum). Needs H, W >= 2 (LangSplat's window is
    empty otherwise and its code raises)."""
    m = np.asarray(mask)
    if m.ndim < 2:
        raise ValueError(f"mask must be [..., H, W], got shape {m.shape}")
    h, w = m.shape[-2:]
    if h < 2 or w < 2:
        raise ValueError(f"majority filter needs an image of at least 2x2 pixels, got {h}x{w}")
    if m.dtype != bool and not np.isin(m, (0, 1)).all():
        raise ValueError("majority filter expects a binary mask")
    # The far row and column never take part, so zero them; then the clipped window is a
    # zero-padded box: an unnormalised box filter with a constant 0 border counts its ones.
    import cv2

    ones = (m != 0).astype(np.uint8).reshape(-1, h, w)
    ones[:, h - 1, :] = 0
    ones[:, :, w - 1] = 0
    size = (2 * radius + 1, 2 * radius + 1)
    count = np.stack(
        [cv2.boxFilter(o, cv2.CV_32S, size, normalize=False, borderType=cv2.BORDER_CONSTANT) for o in ones]
    ).reshape(m.shape)
    i = np.arange(h)
    j = np.arange(w)
    r0, r1 = np.maximum(0, i - radius), np.minimum(i + radius + 1, h - 1)
    c0, c1 = np.maximum(0, j - radius), np.minimum(j + radius + 1, w - 1)
    n = (r1 - r0)[:, None] * (c1 - c0)[None, :]
    return (2 * count > n).astype(np.uint8)  # strictly more ones than zeros; ties -> 0


def segmentation_mask(
    relevancy: np.ndarray,  # [H, W] raw relevancy of one level
    threshold: float = LANGSPLAT_THRESHOLD,
    box_size: int = LANGSPLAT_BOX_SIZE,
    majority_radius: int = LANGSPLAT_MAJORITY_RADIUS,
) -> np.ndarray:  # uint8 [H, W]
    """LangSplat's predicted mask for one level: smooth, normalise, threshold (strict ``>``),
    majority filter."""
    return mask_from_smoothed(smoothed_relevancy(relevancy, box_size), threshold, majority_radius)


def mask_from_smoothed(
    smoothed: np.ndarray,  # [..., H, W] R' = smoothed_relevancy(R), one map or a stack
    threshold: float = LANGSPLAT_THRESHOLD,
    majority_radius: int = LANGSPLAT_MAJORITY_RADIUS,
) -> np.ndarray:  # uint8 [..., H, W]
    binary = normalized_for_threshold(smoothed, stack=np.ndim(smoothed) > 2) > threshold
    return majority_filter(binary, majority_radius)


def mask_iou(pred: np.ndarray, gt: np.ndarray) -> float:  # [H, W], [H, W] -> IoU
    """|pred & gt| / |pred | gt|. Raises on an empty union (LangSplat would produce NaN; the
    protocol never scores a pair whose ground truth is empty)."""
    pred = np.asarray(pred) != 0
    gt = np.asarray(gt) != 0
    if pred.shape != gt.shape:
        raise ValueError(f"mask shapes differ: {pred.shape} vs {gt.shape}")
    union = int(np.logical_or(pred, gt).sum())
    if union == 0:
        raise ValueError("IoU of two empty masks is undefined")
    return int(np.logical_and(pred, gt).sum()) / union


def mask_ious(
    preds: np.ndarray,  # [L, H, W] predicted masks
    gt: np.ndarray,  # [H, W] ground-truth mask, non-empty
) -> np.ndarray:  # float64 [L]
    """:func:`mask_iou` of every mask of a stack against one ground truth."""
    p = np.asarray(preds) != 0
    g = np.asarray(gt) != 0
    if p.shape[1:] != g.shape:
        raise ValueError(f"mask shapes differ: {p.shape[1:]} vs {g.shape}")
    if not g.any():
        raise ValueError("IoU of two empty masks is undefined")
    inter = np.logical_and(p, g).sum(axis=(1, 2))
    union = np.logical_or(p, g).sum(axis=(1, 2))
    return inter / union


def max_locations(filtered: np.ndarray) -> np.ndarray:  # [H, W] -> int64 [P, 2] as (x, y)
    """Every pixel equal to the map's maximum, as (x = column, y = row), like LangSplat's
    ``np.nonzero(map == map.max())`` flipped to x, y."""
    rows, cols = np.nonzero(filtered == filtered.max())
    return np.stack([cols, rows], axis=1)


def localization_maxima(
    relevancy: np.ndarray,  # [H, W] raw relevancy of one map
    box_size: int = LANGSPLAT_BOX_SIZE,
) -> np.ndarray:  # int64 [P, 2] as (x, y), row-major order
    """THE localisation rule (LangSplat's ``lerf_localization``): every maximum of ``box(R)``,
    as integer pixel indices of the map (see the module docstring for the convention)."""
    return max_locations(box_filter(relevancy, box_size))


def localization_point(
    relevancy: np.ndarray,  # [H, W] raw relevancy of one map
    box_size: int = LANGSPLAT_BOX_SIZE,
) -> tuple[int, int]:  # (x, y) integer pixel indices
    """The one point that ``n2f2 query``, the viewer and the evaluation report for a map: the first
    (row-major) of :func:`localization_maxima`."""
    x, y = localization_maxima(relevancy, box_size)[0]
    return int(x), int(y)


# ------------------------------------------------------------------------------ flat maps
def relevancy_range(relevancy: np.ndarray) -> float:  # [...] -> max - min
    """The spread of a relevancy map (or of any set of relevancies, e.g. per Gaussian)."""
    r = np.asarray(relevancy)
    return float(r.max()) - float(r.min())


def is_flat(relevancy: np.ndarray, eps: float = FLAT_RANGE) -> bool:  # [...] -> flat?
    """True when the map's range is below ``eps`` (:data:`FLAT_RANGE`): it carries no signal."""
    return relevancy_range(relevancy) < eps


def flat_warning(
    relevancy: np.ndarray,  # [...] one map, or the relevancy of every Gaussian
    where: str = "this view",
    eps: float = FLAT_RANGE,
) -> Optional[str]:
    """The warning that ``n2f2 query`` prints and writes (and the viewer shows) for a flat map,
    None for a map with signal: ``relevancy is flat over this view (range 2.2e-06 < 1e-03): the
    answer carries no signal``."""
    span = relevancy_range(relevancy)
    if not span < eps:
        return None
    return f"relevancy is flat over {where} (range {span:.1e} < {eps:.0e}): the answer carries no signal"
