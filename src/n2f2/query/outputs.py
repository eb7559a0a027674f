"""What a query writes: raw relevancy (``.npy``), PNG overlays on the rendered RGB, and a JSON
of the numbers. Every picture has its numbers beside it.

Per view ``V`` and query ``Q`` (``<slug>`` = lower-case query, non-alphanumerics -> ``-``):

* ``V_<slug>.npy``: float32 ``[H, W]`` raw relevancy (in (0, 1), 0.5 = as relevant as the
  closest negative phrase).
* ``V_<slug>_heatmap.png``: the relevancy, min-max normalised per map, in the turbo colour map,
  blended over the rendered RGB with opacity proportional to the normalised value. A flat map
  (:func:`n2f2.query.maps.is_flat`) is drawn on the absolute 0..1 scale instead, as one colour
  (:func:`heat_values`), and its record in query.json carries a ``"warning"``.
* ``V_<slug>_mask.png``: the segmentation mask (evaluation-protocol rule) tinted over the RGB,
  with the localization pixel marked by a cross.
* ``V_rgb.png``: the rendered RGB.

2D post-processing (segmentation mask, localization, smoothing) is the evaluation protocol's
(:mod:`n2f2.query.maps`): ``R' = 0.5 (box(R) + R)``, min-max normalise, map to [-1, 1], clip,
``> threshold``, 7x7 majority filter; localization = first maximum of ``box(R)``
(:func:`n2f2.query.maps.localization_point`: integer pixel (x, y) of the view as rendered).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING, Optional, Union

import numpy as np

from ..io import write_json, write_npy, write_png
from .maps import flat_warning, is_flat, localization_point, segmentation_mask

if TYPE_CHECKING:
    from .engine import QueryResult, ViewCache

MASK_COLOR = np.array([0.0, 0.9, 1.0], dtype=np.float32)  # cyan tint of masks (no demo object is cyan)
HEATMAP_ALPHA = 0.8  # opacity of the heatmap over the RGB at normalised relevancy 1 (the viewer uses it too)


def slugify(text: str, max_len: int = 60) -> str:
    """File-name-safe form of a query: ``"Lid of the teapot!"`` -> ``lid-of-the-teapot``."""
    slug = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-")
    return (slug or "query")[:max_len]


def unique_slugs(texts: list[str]) -> list[str]:
    """Slugs, made unique by a numeric suffix when two queries collide."""
    seen: dict[str, int] = {}
    out = []
    for t in texts:
        s = slugify(t)
        n = seen.get(s, 0)
        seen[s] = n + 1
        out.append(s if n == 0 else f"{s}-{n + 1}")
    return out


def segment(relevancy: np.ndarray, box_size: int, threshold: float) -> np.ndarray:  # -> bool [H, W]
    """The protocol's segmentation mask of a relevancy map."""

    return segmentation_mask(relevancy, threshold=threshold, box_size=box_size) != 0


def normalize01(x: np.ndarray) -> np.ndarray:
    """Min-max normalisation to [0, 1] (a constant map becomes 0)."""
    x = np.asarray(x, dtype=np.float32)
    lo, hi = float(x.min()), float(x.max())
    return (x - lo) / (hi - lo) if hi > lo else np.zeros_like(x)


def heat_values(relevancy: np.ndarray) -> np.ndarray:  # [H, W] -> float32 [H, W] in [0, 1]
    """What the heatmap colours: the min-max normalised relevancy, or for a flat map
    (:func:`n2f2.query.maps.is_flat`) its mean relevancy at every pixel, on the absolute 0..1
    scale: one colour (a flat 0.5 map is turbo's middle), not min-max stretched rounding noise
    (which also straddles a colour-map entry at 0.5)."""
    r = np.asarray(relevancy, dtype=np.float32)
    if is_flat(r):
        return np.full_like(r, np.clip(r.mean(dtype=np.float64), 0.0, 1.0))
    return normalize01(r)


def relevancy_colors(
    relevancy: np.ndarray,  # [H, W]
) -> np.ndarray:  # [H, W, 3] float32 in [0, 1]
    """Turbo colours of :func:`heat_values` (the heatmap without the RGB)."""
    from matplotlib import colormaps

    return colormaps["turbo"](heat_values(relevancy))[..., :3].astype(np.float32)


def heatmap_overlay(
    rgb: np.ndarray,  # [H, W, 3] float in [0, 1]
    relevancy: np.ndarray,  # [H, W]
    colors: Optional[np.ndarray] = None,  # [H, W, 3] relevancy_colors(relevancy), when already made
) -> np.ndarray:  # [H, W, 3] float
    """Turbo colours of :func:`heat_values` (the min-max normalised relevancy; absolute for a
    flat map) over the RGB; weak values let the image through (opacity ``HEATMAP_ALPHA`` x value)."""
    v = heat_values(relevancy)
    a = HEATMAP_ALPHA * v[..., None]
    return rgb * (1.0 - a) + (relevancy_colors(relevancy) if colors is None else colors) * a


def mask_overlay(
    rgb: np.ndarray,  # [H, W, 3]
    mask: np.ndarray,  # [H, W] bool
    point: Optional[tuple[int, int]] = None,  # (x, y) localization pixel
) -> np.ndarray:  # [H, W, 3]
    """Mask tinted over a dimmed RGB, the localization pixel marked by a white cross."""
    out = rgb * 0.55
    m = mask[..., None].astype(np.float32)
    out = out * (1.0 - 0.6 * m) + MASK_COLOR * 0.6 * m + rgb * 0.45 * m
    if point is not None:
        H, W = mask.shape
        arm = max(2, min(H, W) // 25)
        x, y = point
        ys = np.arange(max(0, y - arm), min(H, y + arm + 1))
        xs = np.arange(max(0, x - arm), min(W, x + arm + 1))
        out[ys, x] = 1.0
        out[y, xs] = 1.0
    return np.clip(out, 0.0, 1.0)


def write_view_outputs(
    out_dir: Union[str, Path],
    view: ViewCache,
    result: QueryResult,  # for this view
    box_size: int,
    threshold: float,
) -> list[dict]:
    """Write the npy / PNG files of one view and return one JSON record per query."""
    out_dir = Path(out_dir)
    rgb = (
        view.rgb.detach().float().cpu().numpy()
        if view.rgb is not None
        else np.zeros((view.height, view.width, 3), np.float32)
    )
    write_png(out_dir / f"{view.name}_rgb.png", rgb)
    rel_all = result.relevancy.detach().float().cpu().numpy()
    records = []
    for qi, (text, slug) in enumerate(zip(result.texts, unique_slugs(result.texts))):
        rel = np.ascontiguousarray(rel_all[qi], dtype=np.float32)
        mask = segment(rel, box_size, threshold)
        x, y = localization_point(rel, box_size)
        write_npy(out_dir / f"{view.name}_{slug}.npy", rel)
        write_png(out_dir / f"{view.name}_{slug}_heatmap.png", heatmap_overlay(rgb, rel))
        write_png(out_dir / f"{view.name}_{slug}_mask.png", mask_overlay(rgb, mask, (x, y)))
        rec = {
            "view": view.name,
            "view_index": view.index,
            "query": text,
            "files": {
                "relevancy": f"{view.name}_{slug}.npy",
                "heatmap": f"{view.name}_{slug}_heatmap.png",
                "mask": f"{view.name}_{slug}_mask.png",
            },
            "localization": {"x": x, "y": y},
            "relevancy_max": float(rel.max()),
            "relevancy_min": float(rel.min()),
            "relevancy_at_localization": float(rel[y, x]),
            "mask_area_px": int(mask.sum()),
            "mask_area_fraction": float(mask.mean()),
            "chosen_scale": result.chosen_labels[qi],
        }
        if result.scale_scores is not None:
            rec["scale_scores"] = result.scale_scores[qi].detach().float().cpu().tolist()
        warning = flat_warning(rel)
        if warning is not None:  # only for a flat map: the record is otherwise unchanged
            rec["warning"] = warning
        records.append(rec)
    return records


def write_summary(path: Union[str, Path], summary: dict) -> None:
    """The JSON of the numbers (atomic)."""
    write_json(path, summary)
