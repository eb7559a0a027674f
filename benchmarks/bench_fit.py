"""The cpu fit preset on several scenes: total time, step-time spread and quality.

    python benchmarks/bench_fit.py --out /tmp/bench_fit                      # both generated layouts
    python benchmarks/bench_fit.py --out /tmp/bench_fit --scene DATA[:DOWNSCALE] ...  # any scenes

Each scene is fitted with ``n2f2 fit-gaussians DATA --preset cpu`` (sized to the scene by
``FitConfig.sized_for``) in a fresh folder. Prints a Markdown table (steps, Gaussians, held-out
PSNR, median depth error where ground truth exists, wall time, median and 95th-percentile step
time and their ratio) and writes it as ``OUT/bench_fit.json``. Generated layouts are built
first (``n2f2 demo --scene-only``) and reused when already there.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from n2f2.io import write_json


def _n2f2(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "n2f2.cli", *args], check=True)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="work folder")
    p.add_argument("--layouts", nargs="*", default=["tabletop", "lounge"], help="generated layouts to fit")
    p.add_argument("--scene", nargs="*", default=[], metavar="DATA[:DOWNSCALE]", help="other scenes to fit")
    args = p.parse_args()
    out = Path(args.out)
    jobs = []
    for layout in args.layouts:
        demo = out / f"demo_{layout}"
        _n2f2("demo", "--scene-only", "--layout", layout, "--out", str(demo), "--quiet")
        jobs.append((layout, demo / "scene", 1.0))
    for spec in args.scene:
        data, _, ds = spec.partition(":")
        path = Path(data)
        jobs.append((path.parent.name if path.name == "scene" else path.name, path, float(ds or 1)))

    rows = []
    for name, data, ds in jobs:
        fit_dir = out / f"fit_{name}"
        start = time.perf_counter()
        _n2f2("fit-gaussians", str(data), "--out", str(fit_dir), "--downscale", str(ds), "--quiet")
        wall = time.perf_counter() - start
        r = json.loads((fit_dir / "fit_report.json").read_text())
        rows.append({"scene": name, "downscale": ds, "steps": r["steps"], "gaussians": r["num_gaussians"],
                     "test_psnr": r["test_psnr"], "depth_rel_extent": r["depth_median_rel_extent"],
                     "wall_s": wall, "step_median_s": r["step_time_median_s"], "step_p95_s": r["step_time_p95_s"],
                     "threads": r["threads"]})

    print("| scene | steps | Gaussians | held-out PSNR | depth error | wall | step median / p95 | p95 / median |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        depth = "n/a" if r["depth_rel_extent"] is None else f"{100 * r['depth_rel_extent']:.2f} %"
        print(f"| {r['scene']} (/{r['downscale']:g}) | {r['steps']} | {r['gaussians']} | {r['test_psnr']:.2f} dB | "
              f"{depth} | {r['wall_s']:.0f} s | {r['step_median_s'] * 1000:.0f} / {r['step_p95_s'] * 1000:.0f} ms | "
              f"{r['step_p95_s'] / r['step_median_s']:.2f} |")
    write_json(out / "bench_fit.json", rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
