"""Time and peak memory of ``n2f2 decompose`` on a trained run, and on the same run grown to about
a million Gaussians.

    python benchmarks/bench_decompose.py RUN [--gaussians 1000000] [--out DIR]

RUN is a trained run (``make demo`` writes one at demo_out/run). The large case copies RUN's
field and replaces its Gaussians with jittered copies of them (each centre moved by 1 % of the
scene's extent), so the field is read at realistic positions; it measures the command without
``--views``. Each case runs in a fresh process (peak RSS is per process). Prints one JSON line
per case: Gaussians, levels, nodes per level, seconds (the command's own clock and the
process's wall clock), peak RSS in MiB, and the CPU."""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def grow_run(run: Path, out: Path, count: int, seed: int = 0) -> None:
    """``out``: RUN's field with ``count`` jittered copies of its Gaussians."""
    import torch

    from n2f2.gaussians import read_ply, write_ply

    out.mkdir(parents=True)
    shutil.copy2(run / "field.pt", out / "field.pt")
    g = read_ply(run / "gaussians.ply")
    reps = -(-count // g.num)
    idx = torch.arange(g.num).repeat(reps)[:count]
    big = g.subset(idx)
    extent = float((g.means.max(0).values - g.means.min(0).values).norm().detach())
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        big.means.add_(torch.randn(big.means.shape, generator=gen) * 0.01 * extent)
    write_ply(out / "gaussians.ply", big)


def measure(run: Path, out: Path) -> dict:
    """``n2f2 decompose RUN --out OUT`` in a child process: its summary and resources."""
    code = (
        "import json, resource, sys, time\n"
        "from pathlib import Path\n"
        "from n2f2.hierarchy.stage import DecomposeJob, run_decompose\n"
        "t = time.perf_counter()\n"
        f"job = DecomposeJob(Path({str(run)!r}), Path({str(out)!r}), progress=False)\n"
        "rec = run_decompose(job, log=lambda s: None)\n"
        "wall = time.perf_counter() - t\n"
        "rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024\n"
        "print(json.dumps({'gaussians': rec['num_gaussians'], 'levels': rec['num_levels'],"
        " 'nodes': [lv['nodes'] for lv in rec['levels']], 'decompose_s': rec['seconds'],"
        " 'command_s': wall, 'peak_rss_mib': rss}))\n"
    )
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    row = json.loads(res.stdout.strip().splitlines()[-1])
    row["process_s"] = time.perf_counter() - t0
    from n2f2.pipeline.estimate import cpu_name

    row["cpu"] = cpu_name()
    return row


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", type=Path)
    p.add_argument("--gaussians", type=int, default=1_000_000)
    p.add_argument("--out", type=Path, default=None, help="working folder (default: a temporary one, removed)")
    args = p.parse_args()
    work = args.out or Path(tempfile.mkdtemp(prefix="bench_decompose."))
    try:
        print(json.dumps({"case": "run", **measure(args.run, work / "run_decomposition")}), flush=True)
        big = work / "big_run"
        grow_run(args.run, big, args.gaussians)
        print(json.dumps({"case": f"{args.gaussians} Gaussians", **measure(big, work / "big_decomposition")}))
    finally:
        if args.out is None:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
