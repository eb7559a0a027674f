"""Segment extraction serially and as Ray tasks (``n2f2 segments --executor serial|ray``).

The scene is the ``make demo`` scene (``generate_demo_scene`` defaults: 40 views, 160 x 120),
the segmenter the classical one (multi-scale Felzenszwalb). No CLIP weights can be had offline,
so the encoder is a tiny randomly initialised CLIP saved as a folder (``--model DIR``): the
per-image work is the segmenter, the crops and the lifting, not a real CLIP's forward passes,
which would make every image dearer and favour Ray; ``--clip DIR`` takes a CLIP folder instead
(e.g. the full-size random ViT-B/16 of ``make_fullsize_models.py``, with fewer ``--views``).
Depth is the scene's exact depth (``--depth-source gt``), so no Gaussians need fitting.

Measured, each through the command line entry point in this process:

1. serial: ``n2f2 segments`` (scene load, model load, every image, quantile fit);
2. Ray start-up: ``ray.init`` of a local instance with ``--workers`` CPUs plus the round trip of a
   first trivial task (the fixed cost every ``--executor ray`` run pays once);
3. Ray, cold workers: ``n2f2 segments --executor ray`` on that instance, the first time (each
   worker process imports torch and loads the models once);
4. Ray, warm workers: the same again into a new bank (workers kept their models).

    OMP_NUM_THREADS=1 python benchmarks/bench_distributed.py [--workers 2] [--repeats 3] [--out DIR] [--clip DIR --views N]

Serial and warm runs are repeated (``--repeats``) and the minimum is reported: on a shared
machine it is the least disturbed number (all runs are in the JSON). Every bank is checked
equal to the serial one. Numbers go to ``OUT/bench_distributed.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np


def tiny_clip(folder: Path) -> None:
    """A randomly initialised CLIP (2 layers, 32 wide, 16-d embeddings) saved with save_pretrained."""
    import torch
    from transformers import CLIPConfig, CLIPModel, CLIPTokenizer

    torch.manual_seed(0)
    cfg = CLIPConfig(
        text_config=dict(vocab_size=8, hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                         num_attention_heads=2, max_position_embeddings=77, bos_token_id=0, eos_token_id=1,
                         pad_token_id=1),
        vision_config=dict(image_size=32, patch_size=8, hidden_size=32, intermediate_size=64,
                           num_hidden_layers=2, num_attention_heads=2),
        projection_dim=16)
    CLIPModel(cfg).save_pretrained(folder)
    CLIPTokenizer().save_pretrained(folder)


def same_bank(a: Path, b: Path) -> bool:
    meta = json.loads((a / "bank.json").read_text())
    if meta["quantile"] != json.loads((b / "bank.json").read_text())["quantile"]:
        return False
    for image in meta["scene"]["images"]:
        for f in sorted((a / image["name"]).glob("*.npy")):
            x, y = np.load(f), np.load(b / image["name"] / f.name)
            if x.shape != y.shape or not np.array_equal(x, y, equal_nan=x.dtype.kind == "f"):
                return False
    return True


def timed(argv: list[str]) -> float:
    from n2f2.cli import main

    t = time.perf_counter()
    rc = main(argv)
    if rc != 0:
        raise SystemExit(f"n2f2 {' '.join(argv)} exited {rc}")
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--workers", type=int, default=2, help="CPUs of the local Ray instance (default 2)")
    ap.add_argument("--repeats", type=int, default=3, help="runs of the serial and the warm case (default 3)")
    ap.add_argument("--views", type=int, default=40)
    ap.add_argument("--width", type=int, default=160)
    ap.add_argument("--height", type=int, default=120)
    ap.add_argument("--out", default=None, help="working folder (default: a temporary one)")
    ap.add_argument("--clip", default=None, help="CLIP model folder (default: a tiny random CLIP made here)")
    args = ap.parse_args()

    import ray

    from n2f2.data.synthetic import generate_demo_scene

    root = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="bench_distributed_"))
    root.mkdir(parents=True, exist_ok=True)
    scene = root / f"scene-{args.views}x{args.width}x{args.height}"
    clip = Path(args.clip) if args.clip else root / "tiny-clip"
    if not (scene / "scene.json").is_file():
        generate_demo_scene(scene, num_views=args.views, width=args.width, height=args.height, show_progress=False)
    if not (clip / "config.json").is_file():
        tiny_clip(clip)

    def argv(out: str) -> list[str]:
        return ["segments", str(scene), "--segmenter", "classical", "--encoder", "clip", "--model", str(clip),
                "--depth-source", "gt", "--out", str(root / out), "--quiet"]

    def fresh(name: str) -> str:  # a new bank each run: nothing to resume
        if (root / name).exists():
            shutil.rmtree(root / name)
        return name

    serial_runs = [timed(argv(fresh("bank-serial"))) for _ in range(args.repeats)]
    serial = min(serial_runs)

    t = time.perf_counter()
    ray.init(address="local", num_cpus=args.workers, include_dashboard=False, _node_ip_address="127.0.0.1",
             log_to_driver=False)
    t_init = time.perf_counter() - t
    ray.get(ray.remote(lambda: os.getpid()).options(num_cpus=1).remote())
    startup = time.perf_counter() - t
    cold = timed(argv(fresh("bank-ray-cold")) + ["--executor", "ray"])
    warm_runs = [timed(argv(fresh("bank-ray-warm")) + ["--executor", "ray"]) for _ in range(args.repeats)]
    warm = min(warm_runs)
    ray.shutdown()

    same = same_bank(root / "bank-serial", root / "bank-ray-cold") and same_bank(root / "bank-serial",
                                                                               root / "bank-ray-warm")
    encoder = str(clip) if args.clip else "tiny random CLIP (16-d)"
    result = {
        "scene": {"views": args.views, "width": args.width, "height": args.height},
        "segmenter": "classical", "encoder": encoder, "workers": args.workers,
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"), "cpu_count": os.cpu_count(),
        "load_average_1min": os.getloadavg()[0],
        "serial_s": serial, "serial_runs_s": serial_runs, "ray_init_s": t_init, "ray_startup_s": startup,
        "ray_cold_workers_s": cold, "ray_warm_workers_s": warm, "ray_warm_runs_s": warm_runs,
        "speedup_cold_incl_startup": serial / (startup + cold), "speedup_cold": serial / cold,
        "speedup_warm": serial / warm, "banks_identical": same,
    }
    (root / "bench_distributed.json").write_text(json.dumps(result, indent=2) + "\n")
    print(f"segments of the demo scene ({args.views} views {args.width}x{args.height}, classical segmenter, "
          f"CLIP {encoder}), {os.cpu_count()} cores, OMP_NUM_THREADS={result['omp_num_threads']}, "
          f"load average {result['load_average_1min']:.1f}")
    print(f"  serial (min of {args.repeats})             {serial:7.2f} s")
    print(f"  Ray start-up (init + 1st task) {startup:7.2f} s  (ray.init {t_init:.2f} s)")
    print(f"  Ray {args.workers} workers, cold           {cold:7.2f} s  speed-up x{serial / cold:.2f} "
          f"(x{serial / (startup + cold):.2f} with start-up)")
    print(f"  Ray {args.workers} workers, warm (min of {args.repeats}) {warm:7.2f} s  speed-up x{serial / warm:.2f}")
    print(f"  banks identical to serial: {same}; numbers: {root / 'bench_distributed.json'}")


if __name__ == "__main__":
    main()
