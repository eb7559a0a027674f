"""Compare the gsplat (CUDA) backend with the pure-PyTorch backend on the same Gaussians.

Needs a CUDA device and ``pip install gsplat packaging`` (gsplat builds its kernels at first use).

    python benchmarks/compare_gsplat.py                                  # random scenes
    python benchmarks/compare_gsplat.py --scene DATA --gaussians PLY     # a fitted scene, every view

Both backends run on the GPU with gsplat's fixed constants (alpha clamp 0.999, alpha cut 1/255,
transmittance stop 1e-4, 0.3 px dilation). For each case it prints the largest absolute
difference of the feature image, alpha and expected depth, and of the gradients of a random
linear loss with respect to each input (relative to that gradient's largest magnitude), plus the
forward and backward time of each backend (median of 5 after a warm-up).
"""

from __future__ import annotations

import argparse
import statistics
import time
from types import SimpleNamespace

import torch

GSPLAT_ALPHA_CLAMP = 0.999  # built into gsplat's kernels
CASES = [(5_000, 64, 3), (20_000, 128, 3), (20_000, 128, 64), (100_000, 256, 3), (100_000, 256, 64),
         (100_000, 256, 512)]
PARAM_NAMES = ("means", "quats", "scales", "opacities", "features")


def _run(backend: str, params: list, camera, weights: dict, repeats: int) -> dict:
    """Render, backpropagate a fixed random linear loss; time both (CUDA-synchronised)."""
    from n2f2.render import rasterize

    fwd, bwd = [], []
    for _ in range(repeats + 1):  # the first run is a warm-up (and gsplat's JIT build)
        ps = [p.detach().clone().requires_grad_() for p in params]
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        out = rasterize(*ps, camera, backend=backend, alpha_clamp=GSPLAT_ALPHA_CLAMP)
        torch.cuda.synchronize()
        t1 = time.perf_counter()
        loss = ((out.features * weights["features"]).sum() + (out.alpha * weights["alpha"]).sum()
                + (out.depth * weights["depth"]).sum())
        loss.backward()
        torch.cuda.synchronize()
        t2 = time.perf_counter()
        fwd.append(t1 - t0)
        bwd.append(t2 - t1)
    return {"out": out, "grads": [p.grad for p in ps], "fwd_ms": statistics.median(fwd[1:]) * 1e3,
            "bwd_ms": statistics.median(bwd[1:]) * 1e3}


def compare(params: list, camera, repeats: int = 5, seed: int = 0) -> dict:
    """Max abs differences between the two backends for one view (and their timings)."""
    h, w, c = camera.height, camera.width, params[4].shape[1]
    g = torch.Generator(device=params[0].device).manual_seed(seed)
    weights = {"features": torch.rand(h, w, c, generator=g, device=params[0].device),
               "alpha": torch.rand(h, w, 1, generator=g, device=params[0].device),
               "depth": torch.rand(h, w, 1, generator=g, device=params[0].device) * 0.1}
    ref = _run("torch", params, camera, weights, repeats)
    fast = _run("gsplat", params, camera, weights, repeats)
    a, b = (SimpleNamespace(**{k: getattr(r["out"], k).detach() for k in ("features", "alpha", "depth")})
            for r in (ref, fast))
    both = (a.alpha > 0.5) & (b.alpha > 0.5)
    res = {
        "features": float((a.features - b.features).abs().max()),
        "alpha": float((a.alpha - b.alpha).abs().max()),
        "depth_where_alpha>0.5": float(((a.depth - b.depth).abs() * both).max()),
        "features_mean": float((a.features - b.features).abs().mean()),
        "torch_fwd_ms": ref["fwd_ms"], "torch_bwd_ms": ref["bwd_ms"],
        "gsplat_fwd_ms": fast["fwd_ms"], "gsplat_bwd_ms": fast["bwd_ms"],
    }
    for name, ga, gb in zip(PARAM_NAMES, ref["grads"], fast["grads"]):
        scale = float(ga.abs().max()) or 1.0
        res[f"grad_{name}"] = float((ga - gb).abs().max()) / scale
    return res


def _print_table(rows: list[tuple[str, dict]]) -> None:
    grads = [f"grad {n} (rel)" for n in PARAM_NAMES]
    print("| case | image max abs diff | image mean abs diff | alpha max abs diff | depth max abs diff (alpha>0.5) | "
          + " | ".join(grads) + " | torch fwd/bwd ms | gsplat fwd/bwd ms |")
    print("|---" * (8 + len(grads) - 1) + "|")
    for name, r in rows:
        g = " | ".join(f"{r[f'grad_{n}']:.1e}" for n in PARAM_NAMES)
        print(f"| {name} | {r['features']:.1e} | {r['features_mean']:.1e} | {r['alpha']:.1e} "
              f"| {r['depth_where_alpha>0.5']:.1e} | {g} | {r['torch_fwd_ms']:.1f}/{r['torch_bwd_ms']:.1f} "
              f"| {r['gsplat_fwd_ms']:.2f}/{r['gsplat_bwd_ms']:.2f} |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", metavar="DATA", help="scene folder whose cameras to render")
    ap.add_argument("--gaussians", metavar="PLY", help="fitted Gaussians (INRIA PLY) to render with --scene")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per case (median)")
    args = ap.parse_args()
    if args.repeats < 1:
        ap.error("--repeats must be at least 1")
    if not torch.cuda.is_available():
        raise SystemExit("compare_gsplat: needs a CUDA device")
    from n2f2.render.gsplat_backend import gsplat_usable

    device = torch.device("cuda")
    if not gsplat_usable(device):
        raise SystemExit("compare_gsplat: gsplat does not import (pip install gsplat packaging)")
    import gsplat

    print(f"gsplat {gsplat.__version__}, torch {torch.__version__}, {torch.cuda.get_device_name()}")
    rows = []
    if args.scene:
        from n2f2.data import load_scene
        from n2f2.gaussians.ply import read_ply
        from n2f2.render import view_colors

        if not args.gaussians:
            raise SystemExit("compare_gsplat: --scene needs --gaussians")
        scene = load_scene(args.scene)
        gs = read_ply(args.gaussians).to(device)
        for i, cam in enumerate(scene.cameras):
            with torch.no_grad():
                colors = view_colors(gs, cam).clamp_min(0)
            params = [gs.means.detach(), gs.quats.detach(), gs.scales.detach(), gs.opacities.detach(), colors]
            rows.append((f"view {i} ({gs.num} G, {cam.width}x{cam.height}, C=3)", compare(params, cam, args.repeats)))
    else:
        from n2f2.render.reference import random_scene

        for n, size, c in CASES:
            params, cam = random_scene(n, size, c, device=device)
            rows.append((f"random {n}, {size}², C={c}", compare(params, cam, args.repeats)))
    _print_table(rows)
    worst = {k: max(r[k] for _, r in rows) for k in rows[0][1] if not k.endswith("_ms")}
    print("worst over cases:", ", ".join(f"{k} {v:.2e}" for k, v in worst.items()))


if __name__ == "__main__":
    main()
