"""Benchmark of the CPU rasterizer (forward, backward, ns per pixel-Gaussian pair, memory).

    python benchmarks/bench_rasterizer.py                   # 3 scene sizes x C = 3, 64, 512, median of 3
    python benchmarks/bench_rasterizer.py --quick           # 2 smaller scenes x C = 3, 64, one run
    python benchmarks/bench_rasterizer.py --backend torch   # the pure-PyTorch compositing instead

The default backend is ``numba``, the one ``rasterize(backend="auto")`` uses for CPU tensors.

Each case runs in a fresh subprocess so that its peak memory can be read as the growth of the
process's maximum resident set size (``ru_maxrss``) over the value measured just before the
first render: "peak extra RSS". (tracemalloc cannot see torch's allocations.)

Times are wall-clock medians; ``ns/pair`` = (forward + backward wall time) / pixel-Gaussian
pairs walked: for each pixel, the pairs of its tile's list up to where it stops (early
termination), counted by the numba backend's forward pass whichever backend is timed, so both
backends are divided by the same number (the torch backend's own count adds its padding).
``CPU ns/pair`` uses the process CPU time instead (summed over threads); on a shared machine it
is the steadier of the two. ``bwd/fwd`` is the ratio of the two wall times.

The cases run with the caller's ``OMP_WAIT_POLICY`` (OpenMP's default when unset, as the
``n2f2`` batch commands). On an idle machine the default is the fast one; on a machine shared
with other busy processes, ``OMP_WAIT_POLICY=PASSIVE`` or ``--threads 1`` avoids the spin-wait
slowdown (two threads were measured 10x slower than one there).

Scenes are random (:func:`n2f2.render.reference.random_scene`): Gaussians spread through the
view frustum, sized so that each pixel is covered by a few tens of them, like a trained 3DGS.

Each figure is also shown as a ratio to a floor measured in the same process right after the
timed runs, with the same threads, so that the ratios stay comparable on a loaded machine:

* ``fwd floor``: a plain numba loop doing the forward's per-channel work and nothing else, one
  multiply-add per channel (C + 2: features, depth, alpha) for each blended pair (a walked pair
  with alpha >= 1/255), on rows that stay in cache;
* ``bwd floor``: the same for the backward, two multiply-adds per channel and blended pair (the
  feature gradient w * g and the dot product f . g);
* ``mem floor``: one pass over the memory a render must touch at least: the Gaussians'
  features [N, C + 2] read and the image [H, W, C + 2] written (one copy of each).

The multiply-add floors are plain loops, one pair at a time: the backward kernel, which works
on four pixels per pass over the channels, can do its share of that work faster.

The blended pairs are counted by the numba backend's forward
(:func:`n2f2.render.numba_backend.count_pairs`).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import time

SCENES = [(5_000, 64), (20_000, 128), (100_000, 256)]
CHANNELS = [3, 64, 512]
GOAL_NS_PER_PAIR = 20.0
# The goal holds at this case (Gaussians, image side) for these channel counts, with the
# backward at most GOAL_BWD_PER_FWD times the forward.
GOAL_CASE, GOAL_CHANNELS, GOAL_BWD_PER_FWD = (20000, 128), (3, 64), 1.6


def _floor_kernels():
    """Compile the floors' plain loops (numba, the same fast-math flags as the kernels)."""
    import numba
    import numpy as np

    fast = {"reassoc", "contract", "nsz", "arcp"}

    # A function of its own: row views inside a parallel loop's body cost reference counting
    # (measured 2.5x slower), which numba removes in a plain function.
    @numba.njit(fastmath=fast)
    def rows(n, backward, a, g, acc):  # n pairs: acc[i] += w a[j] (forward); also f += a[i] . g[j] (backward)
        w = np.float32(1e-3)
        f = np.float32(0.0)
        for k in range(n):
            i = k & 63
            j = (k * 5 + 3) & 63
            row = acc[i]
            if backward:
                src, other = g[j], a[i]
                for d in range(src.shape[0]):
                    x = src[d]
                    f += other[d] * x
                    row[d] += w * x
            else:
                src = a[j]
                for d in range(src.shape[0]):
                    row[d] += w * src[d]
        return acc.sum() + f

    @numba.njit(parallel=True)
    def madd(n, D, nthreads, backward, sink):  # n pairs of D-channel float32 multiply-adds, 1 or 2 per channel
        for t in numba.prange(nthreads):
            a = np.full((64, D), 0.5, dtype=np.float32)  # feature rows
            g = np.full((64, D), 0.25, dtype=np.float32)  # upstream gradient rows
            acc = np.zeros((64, D), dtype=np.float32)
            sink[t] = rows(n // nthreads + (t < n % nthreads), backward, a, g, acc)

    return madd


def measure_floors(n: int, size: int, D: int, blended: int, threads: int) -> dict:
    """The floors (see the module docstring) in ms: the best of five runs each."""
    import numba
    import numpy as np
    from numba.core import config as numba_config

    n_numba = numba_config.NUMBA_NUM_THREADS  # pyright: ignore[reportAttributeAccessIssue]
    numba.set_num_threads(max(1, min(threads, n_numba)))  # as the numba backend does
    nthreads = numba.get_num_threads()
    madd = _floor_kernels()
    sink = np.zeros(nthreads, dtype=np.float32)
    feats, image = np.random.rand(n, D).astype(np.float32), np.random.rand(size, size, D).astype(np.float32)
    feats_out, image_out = np.empty_like(feats), np.empty_like(image)
    madd(64, D, nthreads, False, sink)  # compile
    madd(64, D, nthreads, True, sink)
    best = {"fwd_floor_ms": math.inf, "bwd_floor_ms": math.inf, "mem_floor_ms": math.inf}
    for _ in range(5):
        t0 = time.perf_counter()
        madd(blended, D, nthreads, False, sink)
        t1 = time.perf_counter()
        madd(blended, D, nthreads, True, sink)
        t2 = time.perf_counter()
        np.copyto(feats_out, feats)
        np.copyto(image_out, image)
        t3 = time.perf_counter()
        for key, dt in (("fwd_floor_ms", t1 - t0), ("bwd_floor_ms", t2 - t1), ("mem_floor_ms", t3 - t2)):
            best[key] = min(best[key], dt * 1e3)
    return best


def run_case(n: int, size: int, channels: int, repeats: int, backend: str) -> dict:
    # As the n2f2 batch commands (see n2f2/cli.py): torch's idle OpenMP threads must not spin
    # through the compiled kernels. Set before torch loads.
    from n2f2.cli import BATCH_SPIN_COUNT

    os.environ.setdefault("GOMP_SPINCOUNT", BATCH_SPIN_COUNT)
    import torch

    from n2f2.render import rasterize
    from n2f2.render.numba_backend import count_pairs
    from n2f2.render.reference import random_scene

    params, camera = random_scene(n, size, channels)
    means, quats, scales, opacities, features = (p.requires_grad_() for p in params)
    cam = camera.to_torch(dtype=means.dtype)
    pairs, blended = count_pairs(means, quats, scales, opacities, features, cam["viewmat"], cam["K"], size, size)
    w = torch.rand(size, size, channels)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    fwd, bwd, cpu = [], [], []
    for _ in range(repeats + 1):  # the first run is a warm-up
        for p in params:
            p.grad = None
        c0 = time.process_time()
        t0 = time.perf_counter()
        out = rasterize(means, quats, scales, opacities, features, camera, backend=backend)
        t1 = time.perf_counter()
        loss = (out.features * w).sum() + out.alpha.sum() + out.depth.sum()
        loss.backward()
        t2 = time.perf_counter()
        cpu.append(time.process_time() - c0)
        fwd.append(t1 - t0)
        bwd.append(t2 - t1)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0
    floors = measure_floors(n, size, channels + 2, blended, torch.get_num_threads())  # after the peak: own buffers
    f, b, c = (statistics.median(x[1:]) for x in (fwd, bwd, cpu))
    return {"n": n, "size": size, "channels": channels, "backend": backend, "fwd_ms": f * 1e3, "bwd_ms": b * 1e3,
            "pairs": pairs, "blended": blended, "ns_per_pair": (f + b) / max(pairs, 1) * 1e9,
            "cpu_ns_per_pair": c / max(pairs, 1) * 1e9, "peak_mib": peak / 1024,
            "threads": torch.get_num_threads(), **floors}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="two smaller scenes, C = 3 and 64, one run each")
    ap.add_argument("--repeats", type=int, default=None, help="timed runs per case (median); default 3, quick 1")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    ap.add_argument("--backend", choices=["numba", "torch"], default="numba", help="CPU backend (default: numba)")
    ap.add_argument("--case", type=str, default=None, help=argparse.SUPPRESS)  # "n,size,channels" (subprocess)
    args = ap.parse_args()
    repeats = args.repeats or (1 if args.quick else 3)
    if args.threads:
        import torch

        torch.set_num_threads(args.threads)
    if args.case:
        n, size, channels = (int(x) for x in args.case.split(","))
        print(json.dumps(run_case(n, size, channels, repeats, args.backend)))
        return
    scenes = SCENES[:2] if args.quick else SCENES
    channels = CHANNELS[:2] if args.quick else CHANNELS
    env = dict(os.environ)
    load = os.getloadavg()[0]
    print(f"{args.backend} backend, {os.cpu_count()} CPUs visible, 1-min load average {load:.1f} at start; "
          f"OMP_WAIT_POLICY={env.get('OMP_WAIT_POLICY', '(OpenMP default)')}; "
          "peak memory = growth of max RSS in a fresh process")
    print()
    print("| Gaussians | image | C | fwd ms | bwd ms | bwd/fwd | pairs walked | ns/pair (fwd+bwd) | CPU ns/pair "
          "| peak extra RSS MiB | blended | fwd floor ms | bwd floor ms | mem floor ms | fwd/floor | bwd/floor "
          "| (fwd+bwd)/mem floor |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    worst, goal_rows = 0.0, []
    for n, size in scenes:
        for c in channels:
            cmd = [sys.executable, __file__, "--case", f"{n},{size},{c}", "--repeats", str(repeats),
                   "--backend", args.backend]
            if args.threads:
                cmd += ["--threads", str(args.threads)]
            res = subprocess.run(cmd, capture_output=True, text=True, check=True, env=env)
            r = json.loads(res.stdout.strip().splitlines()[-1])
            worst = max(worst, r["ns_per_pair"])
            if (n, size) == GOAL_CASE and c in GOAL_CHANNELS:
                goal_rows.append((c, r["ns_per_pair"], r["bwd_ms"] / r["fwd_ms"]))
            print(f"| {n} | {size}x{size} | {c} | {r['fwd_ms']:.0f} | {r['bwd_ms']:.0f} "
                  f"| {r['bwd_ms'] / r['fwd_ms']:.2f} | {r['pairs']:,} | {r['ns_per_pair']:.1f} "
                  f"| {r['cpu_ns_per_pair']:.1f} | {r['peak_mib']:.0f} "
                  f"| {r['blended']:,} | {r['fwd_floor_ms']:.1f} | {r['bwd_floor_ms']:.1f} | {r['mem_floor_ms']:.2f} "
                  f"| {r['fwd_ms'] / r['fwd_floor_ms']:.1f} | {r['bwd_ms'] / r['bwd_floor_ms']:.1f} "
                  f"| {(r['fwd_ms'] + r['bwd_ms']) / r['mem_floor_ms']:.0f} |", flush=True)
    print()
    print(f"worst ns/pair over all cases: {worst:.1f}; torch threads: {r['threads']}")
    if goal_rows:
        n, size = GOAL_CASE
        met = all(ns <= GOAL_NS_PER_PAIR and ratio <= GOAL_BWD_PER_FWD for _, ns, ratio in goal_rows)
        cases = ", ".join(f"C = {c}: {ns:.1f} ns/pair, backward {ratio:.2f}x" for c, ns, ratio in goal_rows)
        print(f"goal at {n} Gaussians, {size}x{size} (<= {GOAL_NS_PER_PAIR:.0f} ns/pair, backward <= "
              f"{GOAL_BWD_PER_FWD}x the forward): {cases}: {'met' if met else 'not met'}")


if __name__ == "__main__":
    main()
