"""The fast SAM / SAM 2 decoders against the models' own forward at full size: on each photo,
the segmenter runs twice on the same model (``fast_decoder`` on and off) and every kept mask
must match: the same counts after each filtering step, the same number of segments, per
segment IoU >= 0.99 and scores within 1e-4 (float32 sums in another order). The suite checks
the same on tiny random models (tests/test_sam_fast.py, tests/test_sam2.py); this is the
once-at-full-size check.

    python benchmarks/make_fullsize_models.py /tmp/fullsize_models --only sam --only sam2.1-hiera-tiny
    python benchmarks/check_fullsize_masks.py --models /tmp/fullsize_models --json /tmp/masks.json

Photos: the first two of ../shared/data/plush-dog/images (or --photos). Exit 1 when a mask
differs.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_PHOTOS = REPO.parent / "shared" / "data" / "plush-dog" / "images"
MODELS = {"sam": "sam-vit-huge", "sam2": "sam2.1-hiera-tiny"}  # segmenter -> folder in --models


def _by_score(segs):
    order = np.argsort(-segs.scores, kind="stable")
    return segs.masks(order.tolist()), segs.scores[order]


def compare(fast, ref) -> dict:
    """Counts and per-segment agreement of two SegmentSets of one image."""
    a, sa = _by_score(fast)
    b, sb = _by_score(ref)
    out = {"segments_fast": int(fast.num_segments), "segments_reference": int(ref.num_segments)}
    if fast.num_segments == ref.num_segments and fast.num_segments:
        iou = (a & b).sum(axis=(1, 2)) / np.maximum(1, (a | b).sum(axis=(1, 2)))
        out.update(min_iou=float(iou.min()), max_score_diff=float(np.abs(sa - sb).max()))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", type=Path, required=True, help="folder of make_fullsize_models.py")
    ap.add_argument("--photos", type=Path, default=DEFAULT_PHOTOS)
    ap.add_argument("--count", type=int, default=2, help="photos to check (default 2)")
    ap.add_argument("--segmenters", nargs="+", default=list(MODELS), choices=list(MODELS))
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    import torch
    from PIL import Image

    from n2f2.segments.segmenters import get_segmenter

    photos = sorted(p for p in args.photos.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png"))[: args.count]
    if not photos:
        print(f"error: {args.photos}: no photos", file=sys.stderr)
        return 2
    result: dict = {"threads": torch.get_num_threads(), "photos": [p.name for p in photos], "runs": []}
    ok = True
    for name in args.segmenters:
        seg = get_segmenter(name, model_id=str(args.models / MODELS[name]))
        fast_settings = seg.settings
        for photo in photos:
            image = np.asarray(Image.open(photo).convert("RGB"), dtype=np.float32) / 255.0
            row: dict = {"segmenter": name, "photo": photo.name}
            for which, fast in (("fast", True), ("reference", False)):
                seg.settings = replace(fast_settings, fast_decoder=fast)
                t0 = time.perf_counter()
                row[which] = seg(image)
                row[f"seconds_{which}"] = round(time.perf_counter() - t0, 1)
                row[f"counts_{which}"] = dict(seg.last_counts)
            seg.settings = fast_settings
            row.update(compare(row.pop("fast"), row.pop("reference")))
            row["same_counts"] = row["counts_fast"] == row["counts_reference"]
            good = (
                row["same_counts"]
                and row["segments_fast"] == row["segments_reference"]
                and row.get("min_iou", 1.0) >= 0.99
                and row.get("max_score_diff", 0.0) <= 1e-4
            )
            row["equal"] = bool(good)
            ok &= good
            result["runs"].append(row)
            print(json.dumps(row))
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    print("all masks equal" if ok else "MASKS DIFFER")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
