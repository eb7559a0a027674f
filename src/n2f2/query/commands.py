"""``n2f2 query``: open-vocabulary queries on a trained run (2D maps and, with ``--3d``, a 3D
selection exported as an INRIA PLY)."""

from __future__ import annotations

import argparse

from ..config import add_config_options
from ..validate import (
    add_device_option,
    finite_float,
    nonneg_int,
    unit_interval,
)


def add_render_option(p: argparse.ArgumentParser) -> None:
    """``--render``: how 2D views get their features (``QueryConfig.render``; default its own)."""
    from .engine import QueryConfig

    add_config_options(p, QueryConfig, ["render"], field_defaults=True)


def add_full_res_option(p: argparse.ArgumentParser) -> None:
    """``--full-res``: views at the images' size; without it at the downscale the run was trained
    at (``n2f2 train --downscale``), the size its Gaussians were fitted at."""
    p.add_argument(
        "--full-res",
        action="store_true",
        help="render views at the images' full size (default: at the --downscale the run was trained at)",
    )


def add_decomposition_option(p: argparse.ArgumentParser) -> None:
    """``--decomposition DIR``: the run's hierarchy that ``--mode node`` answers from."""
    from .engine import QueryConfig

    add_config_options(p, QueryConfig, ["decomposition"], field_defaults=True)


def add_composite_options(p: argparse.ArgumentParser) -> None:
    """``--composite-weights`` (default QueryConfig's) and ``--temperature`` (None: QueryConfig's):
    composite's weights over the scales, read back by :func:`composite_config`."""
    from .engine import QueryConfig

    add_config_options(p, QueryConfig, ["composite_weights"], field_defaults=True)
    add_config_options(p, QueryConfig, ["temperature"])


def composite_config(args: argparse.Namespace) -> dict:
    """The ``QueryConfig`` keywords of :func:`add_composite_options`' flags (an unset temperature
    keeps QueryConfig's, the paper's). A temperature without ``eq6`` would be ignored: refused."""
    from ..errors import InputError

    if args.temperature is not None and args.composite_weights != "eq6":
        raise InputError(None, "--temperature is the T of Eq. 6: give it with --composite-weights eq6")
    config = {"composite_weights": args.composite_weights}
    if args.temperature is not None:
        config["temperature"] = args.temperature
    return config


def box_size_arg(value: str):
    """``--box-size``: a positive number of pixels, or ``scaled`` (``n2f2 query`` and ``n2f2 view``)."""
    if value == "scaled":
        return value
    try:
        v = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"box size must be a positive integer or 'scaled', got {value!r}")
    if v < 1:
        raise argparse.ArgumentTypeError(f"box size must be >= 1, got {v}")
    return v


def register(subparsers) -> None:
    from .engine import MODES, QueryConfig
    from .modes import QUERY_MODES
    from .soft import SOFT_TEMPERATURE

    p = subparsers.add_parser(
        "query",
        help="answer text queries on a trained run: relevancy maps, masks, localization, 3D selection",
        description="Render each view's feature cache once, then answer every query in one pass. "
        "Writes per view and query a raw relevancy .npy, a heatmap and a mask PNG over "
        "the rendered RGB, and OUT/query.json with the numbers. With --3d, also selects "
        "the relevant Gaussians, writes them as OUT/<query>_selection.ply (INRIA 3DGS "
        "layout) and renders the selection's mask into every view.",
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="trained run folder (field.pt + gaussians.ply)")
    p.add_argument("texts", metavar="TEXT", nargs="+", help='text queries, e.g. "lid of the teapot"')
    p.add_argument(
        "--views",
        type=nonneg_int,
        nargs="+",
        default=[0],
        metavar="I",
        help="view indices (sorted image order, 0-based; default 0)",
    )
    p.add_argument(
        "--mode",
        choices=[m for m in MODES if not QUERY_MODES[m].needs_truth],
        default="composite",
        help="composite (default, paper), explicit (best of the D/k scales per query, "
        "LERF/LangSplat), levels (3-level baseline field), soft (every scale weighted by "
        f"softmax(peak / {SOFT_TEMPERATURE:g}) of its highest relevancy; nested and flat fields)",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="output folder")
    p.add_argument(
        "--scene", default=None, metavar="DATA", help="scene folder (default: the scene recorded in the run)"
    )
    p.add_argument(
        "--3d",
        dest="three_d",
        action="store_true",
        help="also select Gaussians per query, export them as PLY and render their masks",
    )
    p.add_argument(
        "--threshold",
        type=finite_float,
        default=None,
        help="3D selection: absolute relevancy threshold (default: the protocol rule on "
        "the Gaussians' relevancy: min-max normalise, map to [-1, 1], > 0.4)",
    )
    p.add_argument(
        "--mask-threshold",
        type=unit_interval,
        default=None,
        help="2D segmentation threshold of the evaluation protocol (default 0.4)",
    )
    p.add_argument(
        "--box-size",
        type=box_size_arg,
        default=None,
        help="protocol mean-filter size in pixels, or 'scaled' = round(30 W / 986) "
        "(default 30, LangSplat's; use 'scaled' on small renders)",
    )
    add_composite_options(p)
    add_render_option(p)
    add_full_res_option(p)
    add_decomposition_option(p)
    p.add_argument("--path", action="store_true", help="with --mode node: print each answer's ancestors, finest first")
    add_config_options(p, QueryConfig, ["canonical"])  # None: QueryConfig's phrases
    add_config_options(p, QueryConfig, ["selection"], field_defaults=True)
    p.add_argument(
        "--force",
        action="store_true",
        help="replace the query results already in --out (query.json and the files it lists)",
    )
    add_device_option(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from .stage import QueryJob, run_query

    composite = composite_config(args)
    run_query(
        QueryJob(
            run_dir=Path(args.run_dir),
            texts=args.texts,
            out=Path(args.out),
            views=args.views,
            mode=args.mode,
            scene=None if args.scene is None else Path(args.scene),
            three_d=args.three_d,
            threshold=args.threshold,
            mask_threshold=args.mask_threshold,
            box_size=args.box_size,
            composite_weights=composite["composite_weights"],
            temperature=composite.get("temperature"),
            render=args.render,
            canonical=tuple(args.canonical) if args.canonical else None,
            selection=args.selection,
            force=args.force,
            device=args.device,
            progress=not args.quiet,
            full_res=args.full_res,
            decomposition=None if args.decomposition is None else Path(args.decomposition),
            path=args.path,
        )
    )
    return 0
