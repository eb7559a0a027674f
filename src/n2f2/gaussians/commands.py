"""``n2f2 fit-gaussians``: fit a 3DGS model to a posed image collection."""

from __future__ import annotations

import argparse

from ..config import add_config_options, add_preset_option, config_overrides, field_default, stage_job_args
from ..validate import add_device_option, finite_float, nonneg_int, positive_float, positive_int, unit_interval


def register(subparsers) -> None:
    from .fit import FitConfig

    p = subparsers.add_parser(
        "fit-gaussians",
        help="fit 3D Gaussians to a scene's images (writes gaussians.ply and fit_report.json)",
        description="Fit a 3D Gaussian Splatting model to a COLMAP or nerfstudio scene. Writes "
        "DIR/gaussians.ply (INRIA 3DGS layout), DIR/fit_report.json and DIR/checkpoint.pt.",
    )
    p.add_argument(
        "data",
        metavar="DATA",
        help="scene folder (COLMAP sparse/0 or nerfstudio transforms.json), "
        "or a folder of photos, posed first by `n2f2 sfm` into DIR/sfm",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    add_preset_option(
        p, f"cpu: a few minutes for small scenes, sized to the scene; paper: 3DGS's {FitConfig.paper().steps} steps"
    )
    # Every option() field of FitConfig (n2f2.config): --steps, --depth-spread, --max-gaussians,
    # --checkpoint-every; None keeps the preset's (or the checkpoint's) value.
    add_config_options(p, FitConfig)
    p.add_argument("--resume", action="store_true", help="continue from DIR/checkpoint.pt")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace the results already in DIR (gaussians.ply, checkpoint.pt, fit_report.json, ...)",
    )
    p.add_argument(
        "--downscale", type=positive_float, default=1.0, help="image downscale factor, as 3DGS -r (default 1)"
    )
    p.add_argument(
        "--init",
        default=None,
        metavar="points|random|PLY",
        help="initialisation: the scene's sparse points, random Gaussians in the camera frusta, or "
        "an INRIA 3DGS PLY trained elsewhere in the same world frame, fitted further "
        "(default: sparse points when the scene has them, else random)",
    )
    seed = field_default(FitConfig, "seed")
    p.add_argument("--seed", type=nonneg_int, default=seed, help=f"random seed (default {seed})")
    p.add_argument(
        "--skip-missing",
        action="store_true",
        help="drop views whose image file is missing (default: a missing image is an error)",
    )
    add_device_option(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)
    _register_render(subparsers)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from .fit import FitConfig
    from .stage import FitJob, run_fit

    run_fit(
        FitJob(
            data=Path(args.data),
            out=Path(args.out),
            preset=args.preset,
            overrides=config_overrides(args, FitConfig),
            init=args.init,
            seed=args.seed,
            **stage_job_args(args),
        )
    )
    return 0


def _register_render(subparsers) -> None:
    p = subparsers.add_parser(
        "render",
        help="render a Gaussian PLY (n2f2's or one trained elsewhere) from a ring of orbit cameras",
        description="Render an INRIA 3DGS PLY (written by n2f2, 3DGS, gsplat or nerfstudio) from NUM cameras "
        "evenly spaced around the Gaussians' robust centre, without the capture's poses. Writes "
        "DIR/orbit_XX.png and the float32 renders DIR/orbit_XX.npy, plus DIR/cameras.json.",
    )
    p.add_argument("ply", metavar="PLY", help="Gaussians in the INRIA 3DGS PLY layout")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument("--views", type=positive_int, default=8, help="number of orbit views (default 8)")
    p.add_argument("--elevation", type=finite_float, default=20.0, help="degrees above the horizon (default 20)")
    p.add_argument(
        "--up",
        type=finite_float,
        nargs=3,
        default=(0.0, -1.0, 0.0),
        metavar=("X", "Y", "Z"),
        help="world up vector (default 0 -1 0: COLMAP worlds, whose cameras look down +z with y down)",
    )
    p.add_argument(
        "--size",
        type=positive_int,
        nargs=2,
        default=(512, 384),
        metavar=("W", "H"),
        help="image width and height in pixels (default 512 384)",
    )
    p.add_argument("--fov", type=positive_float, default=50.0, help="horizontal field of view in degrees (default 50)")
    p.add_argument(
        "--background",
        type=unit_interval,
        nargs=3,
        default=(1.0, 1.0, 1.0),
        metavar=("R", "G", "B"),
        help="background colour in [0, 1] (default white)",
    )
    p.add_argument(
        "--force", action="store_true", help="replace the renders already in DIR (orbit_XX.png / .npy, cameras.json)"
    )
    p.set_defaults(func=run_render)


def run_render(args: argparse.Namespace) -> int:
    import math
    import re
    from pathlib import Path

    from ..errors import InputError
    from ..io import claim_out_dir, remove_results, write_json, write_npy, write_png
    from .orbit import orbit_cameras, render_views
    from .ply import read_ply

    if not 1 <= args.views <= 360:
        raise InputError(None, f"--views must be in [1, 360], got {args.views}")
    w, h = args.size
    if not (8 <= w <= 4096 and 8 <= h <= 4096):
        raise InputError(None, f"--size must be between 8 and 4096 pixels per side, got {w} {h}")
    if not 1.0 <= args.fov <= 170.0:
        raise InputError(None, f"--fov must be in [1, 170] degrees, got {args.fov}")
    if not all(math.isfinite(v) for v in (*args.up, args.elevation)) or not any(args.up):
        raise InputError(None, "--up must be a finite non-zero vector and --elevation finite")
    if not all(0.0 <= v <= 1.0 for v in args.background):
        raise InputError(None, f"--background must be in [0, 1], got {args.background}")
    out = Path(args.out)
    # Every orbit render there, also those of an earlier run with more --views.
    old = (
        sorted(p.name for p in out.glob("orbit_*") if re.fullmatch(r"orbit_\d+\.(png|npy)", p.name))
        if out.is_dir()
        else []
    )
    present = claim_out_dir(out, ["cameras.json", *old], force=args.force, resume_flag=None)
    g = read_ply(args.ply)
    g.sh_degree = g.max_sh_degree
    cameras = orbit_cameras(g, args.views, elevation=args.elevation, up=tuple(args.up), width=w, height=h, fov=args.fov)
    if args.force:  # the PLY is read: now the old renders go
        remove_results(out, present)
    for k, (cam, image) in enumerate(zip(cameras, render_views(g, cameras, tuple(args.background)))):
        write_npy(out / f"orbit_{k:02d}.npy", image)
        write_png(out / f"orbit_{k:02d}.png", image)
    write_json(
        out / "cameras.json",
        [
            {"K": c.K.tolist(), "world_to_camera": c.world_to_camera.tolist(), "width": c.width, "height": c.height}
            for c in cameras
        ],
    )
    print(f"render: {len(cameras)} orbit views of {g.num} Gaussians -> {out}")
    return 0
