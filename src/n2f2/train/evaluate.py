"""How well the trained field reproduces the teacher at each hierarchy level, on held-out views
of a scene with ground-truth regions (the built-in demo scene).

For view v, level l (0 = part, 1 = object, 2 = group) and a ground-truth region R of that level,
the bank segment with the highest IoU with R (at least ``min_iou``) is "the segment covering u
at that level" for every pixel u of R. The score of u is

    cos( phi(u, s), e ),  phi(u, s) = W (B(s) * theta(u))

with ``s`` that segment's quantized scale, ``e`` its teacher embedding and ``theta(u)`` the
test-time rendered feature (MLP per Gaussian, D channels rasterized; no deferral). B(s) is the
field's own variant mask (prefix M(s) for nested, all dims for flat, the scale group's block for
"levels"), i.e. exactly the feature the loss supervised for that segment.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Optional, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from ..field.model import NestedField, gaussian_features
from .geometry import bank_cameras, frozen_geometry, render_features

if TYPE_CHECKING:
    from ..data.scene import Scene

DEFAULT_LEVELS = ("part", "object", "group")


def match_regions_to_segments(
    regions: np.ndarray,  # [H, W] int region id, -1 = none
    layers: np.ndarray,  # [L, H, W] int local segment id, -1 = none
    num_segments: int,
    min_iou: float = 0.5,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Best-IoU bank segment per region. Returns ``(region_ids [R], segment [R] (-1 when no
    segment reaches min_iou), iou [R])``."""
    reg = regions.reshape(-1).astype(np.int64)
    region_ids, reg_index = np.unique(reg, return_inverse=True)
    present = region_ids >= 0
    R, S = len(region_ids), max(int(num_segments), 1)
    inter = np.zeros((R, S), np.int64)
    seg_area = np.zeros(S, np.int64)
    for layer in layers.reshape(layers.shape[0], -1).astype(np.int64):
        on = layer >= 0
        np.add.at(seg_area, layer[on], 1)
        inter += np.bincount(reg_index[on] * S + layer[on], minlength=R * S).reshape(R, S)
    reg_area = np.bincount(reg_index, minlength=R)
    union = reg_area[:, None] + seg_area[None, :] - inter
    iou = inter / np.maximum(union, 1)
    best = iou.argmax(axis=1)
    best_iou = iou[np.arange(R), best]
    best = np.where((best_iou >= min_iou) & present, best, -1)
    return region_ids[present], best[present], best_iou[present]


@torch.no_grad()
def evaluate_cosine_by_level(
    field: NestedField,
    gaussians: Any,  # has means [N, 3], quats, scales, opacities
    scene: Scene,  # with ground_truth
    bank: Any,  # segment bank (record(i) -> layers, embeddings, quantized)
    views: Sequence[int],
    *,
    min_iou: float = 0.5,
    device: str | torch.device = "cpu",
    level_names: Optional[Sequence[str]] = None,
) -> dict:
    """Mean cosine similarity between phi(u, s) and the teacher embedding of the ground-truth
    segment covering u, per hierarchy level (see module docstring). Returns
    ``{"levels": {name: {"cosine": pixel mean, "region_cosine": mean over (view, region),
    "pixels", "regions", "unmatched_regions"}}, "views": [...], "per_view": [{"view": v,
    name: pixel mean in view v or None}, ...]}``. The per-view means show how much one view's
    coarse segments can move a level's mean (a few large segments carry most of its pixels)."""
    from ..segments.segmenters import resize_nearest

    if scene.ground_truth is None:
        raise ValueError("evaluate_cosine_by_level needs a scene with ground-truth regions (the demo scene)")
    names = list(level_names or scene.ground_truth.regions.get("levels", DEFAULT_LEVELS))
    field = field.to(device).eval()
    geometry = frozen_geometry(gaussians, device)
    theta_g = gaussian_features(field, geometry["means"])  # [N, D] test time: MLP per Gaussian
    cameras = bank_cameras(scene, bank)
    sums = {n: [0.0, 0, [], 0] for n in names}  # cos sum, pixels, per-region means, unmatched
    per_view = []
    for v in views:
        per_view.append({"view": int(v), **{n: None for n in names}})
        theta = render_features(geometry, theta_g, cameras[v])  # [H*W, D]
        rec = bank.record(v)
        layers = np.asarray(rec.layers)
        gt = resize_nearest(np.asarray(scene.ground_truth.region_ids(v)), bank.height, bank.width)
        quantized = torch.as_tensor(np.asarray(rec.quantized, dtype=np.float32), device=device)
        embeddings = torch.as_tensor(np.asarray(rec.embeddings, dtype=np.float32), device=device)
        valid = np.asarray(rec.valid, dtype=bool) if getattr(rec, "valid", None) is not None else None
        for level, name in enumerate(names):
            region_ids, seg, _ = match_regions_to_segments(gt[level], layers, len(quantized), min_iou)
            if valid is not None:
                seg = np.where((seg >= 0) & valid[np.maximum(seg, 0)], seg, -1)
            sums[name][3] += int((seg < 0).sum())
            lookup = dict(zip(region_ids.tolist(), seg.tolist()))
            uniq, inverse = np.unique(gt[level].reshape(-1), return_inverse=True)
            seg_of_region = np.array([lookup.get(int(r), -1) for r in uniq], np.int64)  # one per region
            pixel_seg = seg_of_region[inverse.reshape(-1)]  # [H*W] covering segment, -1 = none
            pix = np.nonzero(pixel_seg >= 0)[0]
            if len(pix) == 0:
                continue
            segs = torch.as_tensor(pixel_seg[pix], device=device)
            pix_t = torch.as_tensor(pix, device=device)
            phi = field.project(theta[pix_t], field.supervision_mask(quantized[segs]))  # [P, E]
            cos = F.cosine_similarity(phi, embeddings[segs], dim=-1, eps=1e-8)  # [P]
            sums[name][0] += float(cos.sum())
            per_view[-1][name] = float(cos.mean())
            sums[name][1] += len(pix)
            seg_sum = torch.bincount(segs, weights=cos.double(), minlength=len(quantized))
            seg_count = torch.bincount(segs, minlength=len(quantized))
            sums[name][2].extend((seg_sum[seg_count > 0] / seg_count[seg_count > 0]).tolist())
    levels = {}
    for name, (total, count, per_region, unmatched) in sums.items():
        levels[name] = {
            "cosine": total / count if count else None,
            "region_cosine": float(np.mean(per_region)) if per_region else None,
            "pixels": count,
            "regions": len(per_region),
            "unmatched_regions": unmatched,
        }
    return {"levels": levels, "views": [int(v) for v in views], "per_view": per_view, "min_iou": min_iou}


def cosine_table(results: dict[str, dict]) -> str:
    """Markdown table, one row per run name: pixel-mean cosine per level."""
    names = list(next(iter(results.values()))["levels"])
    lines = ["| run | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for run, res in results.items():
        cells = [
            f"{res['levels'][n]['cosine']:.4f}" if res["levels"][n]["cosine"] is not None else "n/a" for n in names
        ]
        lines.append(f"| {run} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
