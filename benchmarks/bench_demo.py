"""``make demo`` stage by stage, each stage beside a floor measured in the same run.

    python benchmarks/bench_demo.py DEMO_OUT            # a finished `n2f2 demo --out DEMO_OUT`
    python benchmarks/bench_demo.py DEMO_OUT --run      # run `n2f2 demo --out DEMO_OUT` first

Prints the stage times the pipeline recorded (``DEMO_OUT/stages.json``, ``DEMO_OUT/run/stages.json``)
and, for the stages whose cost is a loop of identical steps, the median step beside its floor,
timed here on the same machine right after:

* **fit**: the median optimisation step (``fit_report.json``) against one forward + backward
  pass of the rasterizer over the fitted Gaussians at one training view (the step's own render,
  without the loss, the optimiser and densification);
* **train**: the median training step (``train_report.json``) against the dense arithmetic of one
  step: the field's MLP, forward and backward, on the step's sampled pixels, and the loss's
  projection ``W`` in the field's D dims as the trainer computes it (random inputs of the same
  sizes; no TriPlane, no blending);
* **eval**: per labelled view, the render-and-cache time and the query-and-score time
  (``eval.json``), whose floor is the render.

A ratio near 1 means the stage is as fast as its arithmetic allows at this design; the rest of a
stage's time is what its loop does beyond the floor.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from n2f2.cli import BATCH_SPIN_COUNT

# As the n2f2 batch commands (n2f2/cli.py): torch's idle OpenMP threads must not spin through the
# rasterizer's compiled kernels. Set before torch loads.
os.environ.setdefault("GOMP_SPINCOUNT", BATCH_SPIN_COUNT)
import torch  # noqa: E402


def median_time(fn, repeats: int = 7) -> float:
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def fit_floor(demo: Path) -> float:
    """One rasterizer forward + backward of the fitted Gaussians at the first view's size."""
    from n2f2.data import load_scene
    from n2f2.gaussians import read_ply
    from n2f2.render import render_rgb

    scene = load_scene(demo / "scene")
    g = read_ply(demo / "run" / "gaussians.ply")
    for p in g.parameters():
        p.requires_grad_(True)
    cam = scene.cameras[0]

    def step() -> None:
        out = render_rgb(g, cam)
        out.features.sum().backward()

    return median_time(step)


def train_floor(run: Path) -> float:
    """The dense arithmetic of one training step: the MLP forward and backward on its pixels and
    the loss as the trainer computes it, in the D field dims (``G = W^T W`` and ``u = W^T t`` per
    distinct target; a step's pixels sample a few hundred segments). With every covering segment
    per pixel (``every_segment``), the loss runs on the run's mean rows per step."""
    from n2f2.field.model import prefix_mask
    from n2f2.train.losses import prefix_projected_loss, projected_loss

    report = json.loads((run / "train_report.json").read_text())
    f, t = report["field_config"], report["train_config"]
    E, D, P = int(report["embed_dim"]), int(f["dim"]), int(t["pixels_per_step"])
    every = bool(t.get("every_segment")) and f["variant"] != "levels"
    R = int(round(report.get("rows_per_iteration") or P)) if every else P
    width = int(f["plane_channels"]) if f["backbone"] == "triplane" else 3 * (2 * int(f["pe_frequencies"]) + 1)
    dims = [width] + [int(f["hidden"])] * (int(f["num_layers"]) - 1) + [D]
    layers: list[torch.nn.Module] = []
    for a, b in zip(dims[:-1], dims[1:]):
        layers += [torch.nn.Linear(a, b), torch.nn.ReLU()]
    mlp = torch.nn.Sequential(*layers[:-1])
    W = torch.nn.Parameter(torch.randn(E, D) * 0.01)
    x = torch.randn(P, width)
    targets = torch.randn(512, E)
    index = torch.randint(512, (R,))
    row = torch.arange(R) * P // R  # each pixel's rows side by side, as a batch holds them
    keep = torch.randint(1, D + 1, (R,))  # each row's M(s)
    weight = torch.full((R,), P / R)

    def step() -> None:
        theta = mlp(x)
        if every:
            loss = prefix_projected_loss(theta, row, keep, W, targets, index, 0.001, weight)[0]
        else:
            loss = projected_loss(theta * prefix_mask(keep, D), W, targets, index, 0.001)[0]
        loss.backward()

    return median_time(step)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("demo", type=Path, metavar="DEMO_OUT")
    ap.add_argument("--run", action="store_true", help="run `n2f2 demo --out DEMO_OUT` first")
    args = ap.parse_args()
    demo = args.demo
    if args.run:
        subprocess.run([sys.executable, "-m", "n2f2.cli", "demo", "--out", str(demo)], check=True)
    stages = {}
    for path in (demo / "stages.json", demo / "run" / "stages.json"):
        if path.is_file():
            stages.update({k: v["seconds"] for k, v in json.loads(path.read_text()).items()})
    if not stages:
        raise SystemExit(f"bench_demo: {demo} holds no stages.json (run `n2f2 demo --out {demo}`)")
    run = demo / "run"
    print(f"torch threads: {torch.get_num_threads()}")
    print("\n| stage | seconds |\n|---|---:|")
    for k, v in stages.items():
        print(f"| {k} | {v:.1f} |")
    pipeline = sum(v for k, v in stages.items() if k != "demo-scene")
    print(f"| pipeline (all but demo-scene) | {pipeline:.1f} |")

    print("\n| loop | step ms (median, from the run) | floor ms (timed now) | x floor |\n|---|---:|---:|---:|")
    fit_report = run / "gaussians" / "fit_report.json"
    if fit_report.is_file():
        step = json.loads(fit_report.read_text())["step_time_median_s"]
        floor = fit_floor(demo)
        print(
            f"| fit step vs one rasterizer forward + backward "
            f"| {step * 1e3:.1f} | {floor * 1e3:.1f} | {step / floor:.2f} |"
        )
    train_report = run / "train_report.json"
    if train_report.is_file():
        step = json.loads(train_report.read_text())["time_per_iteration_s"]
        floor = train_floor(run)
        print(f"| train step vs its MLP + projection arithmetic | {step * 1e3:.1f} | {floor * 1e3:.1f} | {step / floor:.2f} |")
    eval_json = run / "eval" / "eval.json"
    if eval_json.is_file():
        views = json.loads(eval_json.read_text())["views"]
        render = statistics.median(v["render_s"] for v in views)
        query = statistics.median(v["query_s"] for v in views)
        print(
            f"| eval view: render + queries vs its render | {(render + query) * 1e3:.0f} | {render * 1e3:.0f} | "
            f"{(render + query) / render:.1f} |"
        )


if __name__ == "__main__":
    main()
