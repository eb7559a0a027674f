"""``n2f2 bench``: the options of the ablation bench (:mod:`.bench`)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

from ..config import add_config_options, config_overrides
from ..errors import InputError
from ..segments.lifting import LiftSettings
from ..validate import add_device_option, composite_temperature, positive_int
from .variants import PAPER_DIM, VARIANTS


def _stage_configs() -> dict[type, tuple[str, ...]]:
    """Settings of the cpu preset's stages the bench can change in every run (BenchConfig fields
    of the same names), by config class: their help, type and choices are the fields' own
    (n2f2.config.option)."""
    from ..train.config import TrainConfig

    return {LiftSettings: ("scale_measure",), TrainConfig: ("scale_jitter",)}


def _add_arguments(p: argparse.ArgumentParser) -> None:
    from .bench import BenchConfig

    full, quick = BenchConfig(), BenchConfig.quick()
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (bench.md, bench.json, runs/, data/)")
    p.add_argument(
        "--scene",
        default=None,
        metavar="DIR",
        help="demo scene folder (default: generate the default demo scene into OUT/data/scene)",
    )
    p.add_argument(
        "--gaussians",
        default=None,
        metavar="PLY",
        help="fitted Gaussians of the scene (default: fit them into OUT/data/gaussians)",
    )
    p.add_argument(
        "--bank",
        default=None,
        metavar="DIR",
        help="segment bank of the scene (default: build it into OUT/data/bank: ground-truth "
        "segments, caption embeddings)",
    )
    p.add_argument(
        "--iterations",
        type=positive_int,
        default=None,
        help=f"training steps per variant (default {full.iterations}; quick {quick.iterations})",
    )
    p.add_argument(
        "--dim",
        type=positive_int,
        default=None,
        help=f"feature dims D of every field (default {full.dim}; quick {quick.dim}; paper {PAPER_DIM}). "
        "k is scaled to keep each paper setting's number of scales",
    )
    p.add_argument(
        "--variants",
        nargs="+",
        choices=list(VARIANTS),
        default=None,
        metavar="NAME",
        help=f"variants to run (default all: {' '.join(VARIANTS)})",
    )
    p.add_argument(
        "--temperatures",
        nargs="+",
        type=composite_temperature,
        default=None,
        metavar="T",
        help=f"composite temperatures evaluated on the N2F2 run (default "
        f"{' '.join('uniform' if math.isinf(t) else f'{t:g}' for t in full.temperatures)}; "
        "1 = paper, uniform = n2f2's default)",
    )
    for cls, names in _stage_configs().items():  # values shown: the bench's (full and --quick)
        add_config_options(p, cls, names, presets={"full": full, "quick": quick})
    p.add_argument(
        "--quick",
        action="store_true",
        help=f"a few minutes: small generated scene, D = {quick.dim}, {quick.iterations} steps",
    )
    add_device_option(p)
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "bench",
        help="reproduce the paper's ablations on the demo scene (bench.md)",
        description="Train N2F2 and its ablations (non-nested, 3-level LangSplat-like, step sizes k, MLP "
        "backbone) on the built-in demo scene, evaluate them and the training-free lift baseline (variant "
        "lift: the nested run's RUN/lift.pt; alone, the bench builds the blending weights itself) with "
        "LangSplat's protocol (exact and scaled box), with the time to build each, time the query modes, "
        "and write OUT/bench.md, OUT/bench.json and plots. Reruns reuse finished runs and evaluations.",
    )
    _add_arguments(p)
    p.set_defaults(func=_cmd_bench)


def _cmd_bench(args: argparse.Namespace) -> int:
    from .bench import BenchConfig, run_bench

    over: dict[str, Any] = {"device": args.device, "progress": not args.quiet}
    for name in ("iterations", "dim"):
        value = getattr(args, name)
        if value is not None:
            if value < 1:
                raise InputError(None, f"--{name} must be >= 1, got {value}")
            over[name] = value
    if args.variants:
        over["variants"] = tuple(args.variants)
    if args.temperatures:
        over["temperatures"] = tuple(args.temperatures)
    for cls, names in _stage_configs().items():
        over.update(config_overrides(args, cls, names))
    try:
        config = BenchConfig.quick(**over) if args.quick else BenchConfig(**over)
    except ValueError as e:
        raise InputError(None, str(e)) from None
    run_bench(
        args.out,
        config,
        scene=args.scene,
        gaussians=args.gaussians,
        bank=args.bank,
        log=(lambda s: None) if args.quiet else print,
    )
    print(f"bench: {Path(args.out) / 'bench.md'}")
    return 0
