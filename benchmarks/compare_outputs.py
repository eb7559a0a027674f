"""Compare two output folders of n2f2 (a run, a demo, a bench) file by file, timings aside.

Used to show that a refactor keeps every output: run the same command on the commit before
and after into two folders, then

    python benchmarks/compare_outputs.py BEFORE AFTER

Every file must exist on both sides and hold the same data:
- JSON: equal after dropping values whose key names a timing (seconds, time, elapsed, ETA,
  rates, dates, the host), at any depth; absolute paths inside BEFORE/AFTER are compared
  relative to the folder; ``stages.json``'s stage keys are left out (they hash files that hold
  timings and absolute paths);
- .npy / .npz: the same dtype, shape and values (NaN equal to NaN);
- .pt: the same structure, every tensor equal in dtype, shape and values (timing keys and
  paths as for JSON);
- .png: the same pixels; .ply and other binary files: the same bytes;
- Markdown and text: reported when they differ but not counted, since their tables hold
  timings (their numbers are in the JSON beside them).

Prints one line per difference and a summary; exit 0 when nothing differs, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

import numpy as np

# Key names whose values are timings or machine facts: dropped before comparing JSON.
TIMING_KEY = re.compile(
    r"(^|_)(seconds?|secs?|time|times|timing|timings|elapsed|wall|eta|duration|date|created|"
    r"finished|started|host|hostname|machine|cpu|threads|pid|it_per_s|per_second|speed|rss|"
    r"memory|peak_rss|gib|mib|mb)($|_)|_s$",
    re.IGNORECASE,
)
# Files that are locks, logs or caches, not outputs.
SKIP_NAME = re.compile(r"(^\.n2f2\.lock$|\.log$|^__pycache__$|\.n2f2-old-\d+$)")
TEXT_SUFFIXES = {".md", ".txt", ".csv", ".html"}
STAGES_FILE = "stages.json"


def _without_keys(records):
    """A stage cache's records without their keys (hashes of files with timings in them)."""
    if not isinstance(records, dict):
        return records
    return {k: ({f: v for f, v in r.items() if f != "key"} if isinstance(r, dict) else r) for k, r in records.items()}


def _files(root: Path) -> set[str]:
    out = set()
    for p in root.rglob("*"):
        if any(SKIP_NAME.search(part) for part in p.relative_to(root).parts):
            continue
        if p.is_file():
            out.add(p.relative_to(root).as_posix())
    return out


def _strip(value, roots: tuple[str, ...]):
    """The JSON value without timing keys, with the compared folders' paths made relative."""
    if isinstance(value, dict):
        return {k: _strip(v, roots) for k, v in value.items() if not TIMING_KEY.search(str(k))}
    if isinstance(value, list):
        return [_strip(v, roots) for v in value]
    if isinstance(value, str):
        for root in roots:
            value = value.replace(root, "<OUT>")
        return value
    return value


def _json_diff(a, b, where: str = "") -> list[str]:
    if type(a) is not type(b) and not (isinstance(a, (int, float)) and isinstance(b, (int, float))):
        return [f"{where or '/'}: {type(a).__name__} vs {type(b).__name__}"]
    if isinstance(a, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                out.append(f"{where}/{k}: only in {'after' if k not in a else 'before'}")
            else:
                out += _json_diff(a[k], b[k], f"{where}/{k}")
        return out
    if isinstance(a, list):
        if len(a) != len(b):
            return [f"{where}: {len(a)} items vs {len(b)}"]
        out = []
        for i, (x, y) in enumerate(zip(a, b)):
            out += _json_diff(x, y, f"{where}[{i}]")
        return out
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return []
    return [] if a == b else [f"{where}: {a!r} vs {b!r}"]


def _arrays_equal(a: np.ndarray, b: np.ndarray) -> str | None:
    if a.dtype != b.dtype or a.shape != b.shape:
        return f"{a.dtype}{list(a.shape)} vs {b.dtype}{list(b.shape)}"
    if a.dtype.kind in "fc":
        equal = np.array_equal(a, b, equal_nan=True)
    else:
        equal = np.array_equal(a, b)
    if equal:
        return None
    if a.dtype.kind in "fciu":
        diff = np.abs(a.astype(np.float64) - b.astype(np.float64))
        return f"values differ (max |diff| {np.nanmax(diff):.3g}, {int(np.count_nonzero(diff))} entries)"
    return "values differ"


def _torch_diff(a, b, where: str = "", roots: tuple[str, ...] = ()) -> list[str]:
    """Differences between two loaded ``.pt`` objects: tensors exactly, timing keys dropped,
    the compared folders' paths made relative (as for JSON)."""
    import torch

    if isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor):
        why = _arrays_equal(a.detach().cpu().numpy(), b.detach().cpu().numpy())
        return [] if why is None else [f"{where or '/'}: {why}"]
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return [f"{where or '/'}: keys {sorted(set(a) ^ set(b), key=str)} on one side only"]
        keys = [k for k in sorted(a, key=str) if not TIMING_KEY.search(str(k))]
        return [d for k in keys for d in _torch_diff(a[k], b[k], f"{where}/{k}", roots)]
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            return [f"{where}: {len(a)} items vs {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _torch_diff(x, y, f"{where}[{i}]", roots)]
    if isinstance(a, dict) or isinstance(a, (list, tuple)) or isinstance(a, torch.Tensor):
        return [f"{where or '/'}: {type(a).__name__} vs {type(b).__name__}"]
    if isinstance(a, str) and isinstance(b, str):
        a, b = _strip(a, roots), _strip(b, roots)
    if isinstance(a, str) or isinstance(a, (int, float, bool)) or a is None:
        same = a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b))
        return [] if same else [f"{where}: {a!r} vs {b!r}"]
    return []  # other pickled objects are not outputs anyone reads


def compare_file(before: Path, after: Path, roots: tuple[str, ...]) -> tuple[list[str], bool]:
    """Differences between two files of the same name, and whether they count."""
    suffix = before.suffix.lower()
    if suffix == ".json":
        a = _strip(json.loads(before.read_text()), roots)
        b = _strip(json.loads(after.read_text()), roots)
        if before.name == STAGES_FILE:  # a stage key hashes files that hold timings and paths
            a, b = _without_keys(a), _without_keys(b)
        return _json_diff(a, b), True
    if suffix == ".npy":
        why = _arrays_equal(np.load(before, allow_pickle=False), np.load(after, allow_pickle=False))
        return ([] if why is None else [why]), True
    if suffix == ".npz":
        with np.load(before, allow_pickle=False) as za, np.load(after, allow_pickle=False) as zb:
            if set(za.files) != set(zb.files):
                return [f"arrays {sorted(set(za.files) ^ set(zb.files))} on one side only"], True
            out = []
            for k in sorted(za.files):
                why = _arrays_equal(za[k], zb[k])
                if why is not None:
                    out.append(f"{k}: {why}")
            return out, True
    if suffix == ".pt":
        import torch

        a = torch.load(before, map_location="cpu", weights_only=False)
        b = torch.load(after, map_location="cpu", weights_only=False)
        return _torch_diff(a, b, roots=roots), True
    if suffix == ".png":
        from PIL import Image

        why = _arrays_equal(np.asarray(Image.open(before)), np.asarray(Image.open(after)))
        return ([] if why is None else [f"pixels: {why}"]), True
    if suffix in TEXT_SUFFIXES:
        la, lb = before.read_text(errors="replace").splitlines(), after.read_text(errors="replace").splitlines()
        n = sum(x != y for x, y in zip(la, lb)) + abs(len(la) - len(lb))
        return ([] if n == 0 else [f"{n} lines differ (text: timings expected; not counted)"]), False
    same = before.read_bytes() == after.read_bytes()
    return ([] if same else ["bytes differ"]), True


def compare_dirs(before: Path, after: Path) -> tuple[int, int, list[str]]:
    """(files compared, files that differ and count, report lines)."""
    fa, fb = _files(before), _files(after)
    lines = [f"only in {before}: {p}" for p in sorted(fa - fb)]
    lines += [f"only in {after}: {p}" for p in sorted(fb - fa)]
    bad = len(fa ^ fb)
    roots = (str(before.resolve()), str(after.resolve()), str(before), str(after))
    for rel in sorted(fa & fb):
        diffs, counts = compare_file(before / rel, after / rel, roots)
        if diffs:
            bad += counts
            shown = diffs[:5] + ([f"... {len(diffs) - 5} more"] if len(diffs) > 5 else [])
            lines += [f"{rel}: {d}" for d in shown]
    return len(fa & fb), bad, lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("before", type=Path)
    ap.add_argument("after", type=Path)
    args = ap.parse_args(argv)
    for d in (args.before, args.after):
        if not d.is_dir():
            print(f"error: {d}: not a folder", file=sys.stderr)
            return 2
    n, bad, lines = compare_dirs(args.before, args.after)
    for line in lines:
        print(line)
    print(f"{n} files compared, {bad} differ")
    return 0 if bad == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
