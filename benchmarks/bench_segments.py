"""Segment-stage benchmark.

1. Time per image of the ``classical`` segmenter (multi-scale Felzenszwalb, the weights-free
   fallback for SAM) on 640 x 480 photos from scikit-image (``coffee``, ``astronaut``).
2. LangSplat's mask NMS (``preprocess.py: mask_nms``, SAM masks of one level, run with
   LangSplat's ``masks_update`` thresholds 0.8 / 0.7 / 0.5): n2f2's vectorised version
   (:func:`n2f2.segments.segmenters.mask_nms`, one matrix product for all pairwise
   intersections) against a literal port of LangSplat's Python double loop over mask pairs,
   on N random box masks of 640 x 480. Both must keep the same masks; the loop is quadratic in
   N and slow, so it runs only for N up to ``--loop-max``.

    python benchmarks/bench_segments.py [--repeats 3] [--nms-sizes 16 32 64 128 256] [--loop-max 64]

Times are wall-clock minimum (and CPU time) over ``--repeats`` runs after one warm-up; on a
shared machine the minimum is the least disturbed number.
"""

from __future__ import annotations

import argparse
import time
from typing import Callable

import numpy as np
import torch


def timeit(fn: Callable[[], object], repeats: int) -> tuple[float, float, object]:
    """(min wall s, min CPU s, last result) over ``repeats`` calls after one warm-up call."""
    result = fn()
    wall, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        result = fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return min(wall), min(cpu), result


def photo(name: str, height: int = 480, width: int = 640) -> np.ndarray:  # -> [H, W, 3] float32
    from skimage import data
    from skimage.transform import resize

    return resize(getattr(data, name)(), (height, width), anti_aliasing=True).astype(np.float32)


def bench_classical(repeats: int) -> None:
    from n2f2.segments.segmenters import ClassicalSegmenter

    seg = ClassicalSegmenter()
    print(f"classical segmenter {seg.spec}")
    for name in ("coffee", "astronaut"):
        image = photo(name)  # decoded and resized outside the timing
        wall, cpu, out = timeit(lambda: seg(image), repeats)
        per_layer = [int(np.unique(layer[layer >= 0]).size) for layer in out.layers]
        print(f"  {name} 640x480: {wall:.2f} s/image wall, {cpu:.2f} s CPU; {out.num_segments} segments "
              f"(per scale {per_layer})")


def langsplat_mask_nms_loop(masks: torch.Tensor,  # [N, H, W] bool
                            scores: torch.Tensor,  # [N]
                            iou_thr: float = 0.7, score_thr: float = 0.1, inner_thr: float = 0.2) -> torch.Tensor:
    """LangSplat's ``preprocess.py: mask_nms``, ported literally (Python double loop over mask
    pairs, one full-image logical and/or per pair): the baseline being replaced."""
    scores, idx = scores.sort(0, descending=True)
    n = idx.shape[0]
    masks_ord = masks[idx.view(-1)]
    area = torch.sum(masks_ord, dim=(1, 2), dtype=torch.float)
    iou_matrix = torch.zeros((n, n), dtype=torch.float)
    inner_matrix = torch.zeros((n, n), dtype=torch.float)
    for i in range(n):
        for j in range(i, n):
            inter = torch.sum(torch.logical_and(masks_ord[i], masks_ord[j]), dtype=torch.float)
            union = torch.sum(torch.logical_or(masks_ord[i], masks_ord[j]), dtype=torch.float)
            iou_matrix[i, j] = inter / union
            if inter / area[i] < 0.5 and inter / area[j] >= 0.85:
                inner_matrix[i, j] = 1 - (inter / area[j]) * (inter / area[i])
            if inter / area[i] >= 0.85 and inter / area[j] < 0.5:
                inner_matrix[j, i] = 1 - (inter / area[j]) * (inter / area[i])
    iou_max = iou_matrix.triu(diagonal=1).max(dim=0).values
    inner_u = torch.triu(inner_matrix, diagonal=1).max(dim=0).values
    inner_l = torch.tril(inner_matrix, diagonal=1).max(dim=0).values
    keep = iou_max <= iou_thr
    keep_conf = scores > score_thr
    keep_u = inner_u <= 1 - inner_thr
    keep_l = inner_l <= 1 - inner_thr
    for k in (keep_conf, keep_u, keep_l):  # LangSplat: the top 3 pass a criterion nobody passes
        if k.sum() == 0:
            k[scores.topk(min(3, n)).indices] = True
    return idx[keep & keep_conf & keep_u & keep_l]


def random_masks(n: int, height: int = 480, width: int = 640, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """n random box masks [n, H, W] (nested and overlapping ones occur) and scores [n]."""
    rng = np.random.default_rng(seed)
    y0 = rng.integers(0, height - 20, n)
    x0 = rng.integers(0, width - 20, n)
    y1 = rng.integers(y0 + 10, height)
    x1 = rng.integers(x0 + 10, width)
    ys, xs = np.arange(height)[None, :, None], np.arange(width)[None, None, :]
    m = ((ys >= y0[:, None, None]) & (ys < y1[:, None, None]) & (xs >= x0[:, None, None]) & (xs < x1[:, None, None]))
    return torch.from_numpy(m), torch.from_numpy(rng.uniform(size=n)).float()


def bench_nms(sizes: list[int], loop_max: int, repeats: int) -> None:
    from n2f2.segments.segmenters import mask_nms

    thr = (0.8, 0.7, 0.5)  # LangSplat's masks_update settings
    print(f"mask NMS on 640x480 masks (iou {thr[0]}, score {thr[1]}, inner {thr[2]}), "
          f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    for n in sizes:
        masks, scores = random_masks(n)
        wall, cpu, fast = timeit(lambda: mask_nms(masks, scores, *thr), repeats)
        line = f"  N={n:4d}: vectorised {wall * 1000:8.1f} ms wall ({cpu * 1000:.0f} ms CPU)"
        if n <= loop_max:
            lwall, lcpu, slow = timeit(lambda: langsplat_mask_nms_loop(masks, scores.clone(), *thr), max(1, repeats // 3))
            same = fast.tolist() == slow.tolist()
            line += f"; LangSplat loop {lwall:8.2f} s wall ({lcpu:.1f} s CPU); x{lwall / wall:.0f}; same kept set: {same}"
        print(line + f"; kept {len(fast)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--nms-sizes", type=int, nargs="+", default=[16, 32, 64, 128, 256])
    ap.add_argument("--loop-max", type=int, default=64, help="largest N the double loop runs on")
    ap.add_argument("--skip-classical", action="store_true")
    args = ap.parse_args()
    if not args.skip_classical:
        bench_classical(args.repeats)
    bench_nms(args.nms_sizes, args.loop_max, args.repeats)


if __name__ == "__main__":
    main()
