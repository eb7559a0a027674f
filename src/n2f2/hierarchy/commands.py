"""``n2f2 decompose``: a run's class-agnostic hierarchy of parts, objects and groups."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..config import add_config_options, config_overrides
from ..validate import add_device_option
from .build import DecomposeConfig
from .files import DEFAULT_OUT
from .stage import ALL_VIEWS, DecomposeJob, run_decompose


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "decompose",
        help="place every Gaussian in one tree of parts, objects and groups (no text involved)",
        description="Read the trained nested field at every Gaussian's centre along its scale ladder, "
        "group the Gaussians whose features agree, scale by scale (each node inside one node of the "
        "coarser level), and write tree.json, gaussian_nodes.npy, node_embeddings.npy and "
        "decomposition.ply (the Gaussians with one node_<level> property per level); with --views, "
        "each view's node id per pixel and level. `n2f2 query --mode node` answers with its nodes.",
    )
    p.add_argument("run", metavar="RUN", help="trained run folder (field.pt + gaussians.ply)")
    p.add_argument("--out", metavar="DIR", default=None, help=f"output folder (default RUN/{DEFAULT_OUT})")
    p.add_argument(
        "--vocabulary",
        metavar="FILE",
        default=None,
        help="one phrase a line: each node's best-matching phrase and its relevancy go into tree.json",
    )
    p.add_argument(
        "--views",
        metavar="STEM",
        nargs="+",
        default=(),
        help=f"image stems (or '{ALL_VIEWS}') to write views/<stem>/levels.npy and a PNG per level for",
    )
    p.add_argument("--scene", metavar="DATA", default=None, help="scene folder for --views (default: the run's)")
    add_config_options(p, DecomposeConfig)
    p.add_argument("--force", action="store_true", help="replace the decomposition already in DIR")
    add_device_option(p, "")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_command)


def run_command(args: argparse.Namespace) -> int:
    from dataclasses import replace

    job = DecomposeJob(
        run_dir=Path(args.run),
        out=None if args.out is None else Path(args.out),
        vocabulary=None if args.vocabulary is None else Path(args.vocabulary),
        views=tuple(args.views),
        scene=None if args.scene is None else Path(args.scene),
        config=replace(DecomposeConfig(), **config_overrides(args, DecomposeConfig)),
        device=args.device,
        force=args.force,
        progress=not args.quiet,
    )
    run_decompose(job)
    return 0
