"""``n2f2 inspect``: load a scene and print what n2f2 sees in it."""

from __future__ import annotations

import argparse
import json

from ..config import add_config_options
from ..validate import positive_float


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "inspect",
        help="load a scene (COLMAP or nerfstudio) and print a summary",
        description="Load a scene folder the way training does (same checks, same undistortion, "
        "same downscaling) and print views, image size, intrinsics, lens undistortion, "
        "sparse points, ground truth and bounds.",
    )
    p.add_argument("data", metavar="DATA", help="scene folder (with transforms.json or sparse/0/)")
    p.add_argument(
        "--downscale", "-r", type=positive_float, default=1.0, help="image downscale factor, as 3DGS -r (default: 1)"
    )
    p.add_argument(
        "--format",
        choices=("auto", "colmap", "nerfstudio"),
        default="auto",
        help="scene format; auto prefers transforms.json over COLMAP (default: auto)",
    )
    p.add_argument(
        "--skip-missing",
        action="store_true",
        help="drop views whose image file is missing (default: a missing image is an error)",
    )
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run_inspect)
    register_sfm(subparsers)


def summarize(scene) -> dict:
    """Plain-dict summary of a :class:`~n2f2.data.Scene` (what ``n2f2 inspect`` prints)."""
    import numpy as np

    cams = scene.cameras
    sizes = sorted({(c.width, c.height) for c in cams})

    def value_range(values) -> list[float]:
        return [float(min(values)), float(max(values))]

    lo, hi = scene.scene_bounds()
    user_paths = scene.original_image_paths or scene.image_paths
    cache = next((p.parent.parent for p, o in zip(scene.image_paths, user_paths) if p != o), None)
    return {
        "root": str(scene.root),
        "format": scene.source_format,
        "views": len(scene),
        "downscale": scene.downscale,
        "image_sizes": [list(s) for s in sizes],
        "image_folder": sorted(
            {
                str(p.parent.relative_to(scene.root)) if p.is_relative_to(scene.root) else str(p.parent)
                for p in user_paths
            }
        ),
        "first_image": user_paths[0].name,
        "last_image": user_paths[-1].name,
        "fx": value_range([c.fx for c in cams]),
        "fy": value_range([c.fy for c in cams]),
        "cx": value_range([c.cx for c in cams]),
        "cy": value_range([c.cy for c in cams]),
        "undistorted_views": scene.num_undistorted,
        "undistorted_from": scene.undistorted_from,
        "undistorted_cache": None if cache is None else str(cache),
        "points": 0 if scene.points is None else int(len(scene.points)),
        "point_colors": scene.point_colors is not None,
        "ground_truth": scene.ground_truth is not None,
        "bounds_of": "points" if scene.points is not None and len(scene.points) else "camera centres",
        "bounds_min": np.round(lo, 6).tolist(),
        "bounds_max": np.round(hi, 6).tolist(),
        "extent": scene.extent(),
    }


def run_inspect(args: argparse.Namespace) -> int:
    from . import load_scene

    scene = load_scene(args.data, downscale=args.downscale, format=args.format, skip_missing=args.skip_missing)
    info = summarize(scene)
    if args.json:
        print(json.dumps(info, indent=2))
        return 0

    def rng(key: str) -> str:
        a, b = info[key]
        return f"{a:.6g}" if a == b else f"{a:.6g} .. {b:.6g}"

    sizes = ", ".join(f"{w}x{h}" for w, h in info["image_sizes"])
    points = (
        "none"
        if not info["points"]
        else (f"{info['points']}" + (" (with colours)" if info["point_colors"] else " (no colours)"))
    )
    print(f"scene        {info['root']}")
    print(f"format       {info['format']}")
    print(
        f"views        {info['views']}  ({info['first_image']} .. {info['last_image']} "
        f"in {', '.join(info['image_folder'])})"
    )
    print(f"image size   {sizes}  (downscale {info['downscale']:g})")
    print(f"intrinsics   fx {rng('fx')}, fy {rng('fy')}, cx {rng('cx')}, cy {rng('cy')}")
    if info["undistorted_views"]:
        print(
            f"undistorted  {info['undistorted_views']} views from {info['undistorted_from']} to pinhole "
            f"(cached in {info['undistorted_cache']})"
        )
    print(f"points       {points}")
    print(f"ground truth {'yes' if info['ground_truth'] else 'no'}")
    lo = ", ".join(f"{v + 0.0:.4g}" for v in info["bounds_min"])
    hi = ", ".join(f"{v + 0.0:.4g}" for v in info["bounds_max"])
    print(f"bounds       [{lo}] .. [{hi}]  ({info['bounds_of']})")
    print(f"extent       {info['extent']:.4g}  (3DGS: 1.1 x max camera distance from their mean)")
    return 0


# ----------------------------------------------------------------------------- n2f2 sfm
def register_sfm(subparsers: argparse._SubParsersAction) -> None:
    from .sfm import SfmSettings

    p = subparsers.add_parser(
        "sfm",
        help="pose a folder of photos with structure from motion (pycolmap) and write a COLMAP scene",
        description="Structure from motion with pycolmap: SIFT features, matching, incremental mapping "
        "(the largest model is kept) and undistortion to PINHOLE. Writes DATA/images, "
        "DATA/sparse/0 (the layout `n2f2 inspect`, `fit-gaussians` and `run` read) and "
        "DATA/sfm_report.json. Rerunning on unchanged photos and settings reuses the result.",
    )
    p.add_argument("photos", metavar="PHOTOS", help="folder of photos (directly inside, or in PHOTOS/images)")
    p.add_argument("--out", required=True, metavar="DATA", help="output scene folder")
    # SfmSettings' option() fields, defaulting to its own values (the flags are read as they are).
    add_config_options(p, SfmSettings, ["matcher", "camera_model"], field_defaults=True)
    p.add_argument(
        "--per-image-camera",
        action="store_true",
        help="estimate intrinsics per photo instead of one camera shared by all",
    )
    add_config_options(p, SfmSettings, ["max_image_size"], field_defaults=True)
    p.add_argument(
        "--force",
        dest="overwrite",
        action="store_true",
        help="replace a finished result in DATA made from other photos or settings",
    )
    # The earlier name of --force (every other command says --force): still accepted for one
    # release, no longer listed.
    p.add_argument("--overwrite", dest="overwrite", action="store_true", help=argparse.SUPPRESS)
    p.add_argument(
        "--keep-partial",
        action="store_true",
        help="keep the working folder DATA.partial when structure from motion fails (default: removed)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=run_sfm_command)


def run_sfm_command(args: argparse.Namespace) -> int:
    from .sfm import SfmSettings, run_sfm

    settings = SfmSettings(
        matcher=args.matcher,
        camera_model=args.camera_model,
        per_image_camera=args.per_image_camera,
        max_image_size=args.max_image_size,
    )
    report = run_sfm(
        args.photos,
        args.out,
        settings,
        overwrite=args.overwrite,
        keep_partial=args.keep_partial,
        progress=not args.quiet,
    )
    print(report.summary())
    return 0
