"""``n2f2 fit-gaussians``: fit a 3DGS model to a posed image collection."""

from __future__ import annotations

import argparse


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "fit-gaussians",
        help="fit 3D Gaussians to a scene's images (writes gaussians.ply and fit_report.json)",
        description="Fit a 3D Gaussian Splatting model to a COLMAP or nerfstudio scene. Writes "
                    "DIR/gaussians.ply (INRIA 3DGS layout), DIR/fit_report.json and DIR/checkpoint.pt.",
    )
    p.add_argument("data", metavar="DATA", help="scene folder (COLMAP sparse/0 or nerfstudio transforms.json)")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--preset", choices=["cpu", "paper"], default="cpu",
                   help="cpu: a few minutes for small scenes (default); paper: 3DGS's 30k steps")
    p.add_argument("--steps", type=int, default=None, help="number of optimisation steps (overrides the preset)")
    p.add_argument("--resume", action="store_true", help="continue from DIR/checkpoint.pt")
    p.add_argument("--downscale", type=float, default=1.0, help="image downscale factor, as 3DGS -r (default 1)")
    p.add_argument("--init", choices=["points", "random"], default=None,
                   help="initialisation (default: sparse points when the scene has them, else random)")
    p.add_argument("--checkpoint-every", type=int, default=None, metavar="N",
                   help="write a checkpoint every N steps (default: the preset's; 0: only at the end)")
    p.add_argument("--max-gaussians", type=int, default=None, metavar="N", help="cap on the Gaussian count")
    p.add_argument("--depth-spread", type=float, default=None, metavar="W", dest="depth_spread_weight",
                   help="weight of the depth-spread regulariser (cpu preset 1.5, paper 0 = off as 3DGS)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from ..data import load_scene
    from ..errors import InputError
    from .fit import FitConfig, fit_gaussians, saved_config

    for name, flag in (("steps", "--steps"), ("checkpoint_every", "--checkpoint-every"),
                       ("max_gaussians", "--max-gaussians"), ("depth_spread_weight", "--depth-spread")):
        value = getattr(args, name)
        if value is not None and not value >= 0:  # NaN too
            raise InputError(None, f"{flag} must be >= 0, got {value}")
    if args.downscale <= 0:
        raise InputError(None, f"--downscale must be > 0, got {args.downscale}")
    # A resumed run keeps the checkpoint's schedule; only explicit flags change it.
    base = saved_config(args.out) if args.resume else None
    config = base or replace(FitConfig.preset(args.preset), seed=args.seed)
    config = replace(config, device=args.device)
    overrides = {k: getattr(args, k) for k in ("steps", "checkpoint_every", "max_gaussians", "depth_spread_weight")
                 if getattr(args, k) is not None}
    config = replace(config, **overrides)
    scene = load_scene(args.data, downscale=args.downscale)
    report = fit_gaussians(scene, config, args.out, resume=args.resume, init=args.init, progress=not args.quiet)
    test = "n/a" if report.test_psnr is None else f"{report.test_psnr:.2f} dB"
    depth = "" if report.depth_median_rel_extent is None else \
        f", median depth error {100 * report.depth_median_rel_extent:.2f}% of extent"
    print(f"fit-gaussians: {report.steps} steps, {report.num_gaussians} Gaussians, "
          f"train PSNR {report.train_psnr:.2f} dB, test PSNR {test}{depth}, "
          f"{report.wall_time_s:.0f} s -> {args.out}")
    return 0
