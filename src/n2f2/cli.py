"""The ``n2f2`` command line. Each stage registers its own subcommands in ``<stage>/commands.py``
(a ``register(subparsers)`` function); this file only assembles them and turns user errors into
one clear line and a non-zero exit, without a traceback."""

from __future__ import annotations

import argparse
import os
import sys

# OpenMP reads its wait policy once, when torch loads, so it is chosen before any stage module
# is imported. Batch commands (fit, train, demo, run, ...) let torch's idle OpenMP threads spin
# for GOMP_SPINCOUNT iterations before they sleep: with OpenMP's own, much longer default they
# spin while the CPU rasterizer's compiled kernels run on their own threads, and sleeping at
# once (PASSIVE) slows field training (docs/measurements.md, "OpenMP spin-wait"). The viewer
# computes while other request threads run, so it waits passively. Setting OMP_WAIT_POLICY or
# GOMP_SPINCOUNT yourself overrides both; when several jobs share 2 cores,
# OMP_WAIT_POLICY=PASSIVE or OMP_NUM_THREADS=1 avoids the spin-wait slowdown.
PASSIVE_WAIT_COMMANDS = ("view",)
SERVER_COMMANDS = ("view",)  # run until stopped; what they write is never undone
BATCH_SPIN_COUNT = "100000"

from . import __version__  # noqa: E402 (after the wait-policy notes above; imports no torch)
from .errors import N2F2Error  # noqa: E402
from .heap import keep_freed_blocks  # noqa: E402
from .validate import OneLineArgumentParser  # noqa: E402


def command_modules() -> tuple:
    """Each stage's ``commands`` module, in data-flow order. Imported here, not at the top of
    this file: they import torch, which must load after the OpenMP wait policy is chosen."""
    from .data import commands as data_commands
    from .eval import commands as eval_commands
    from .experiments import commands as experiments_commands
    from .gaussians import commands as gaussians_commands
    from .hierarchy import commands as hierarchy_commands
    from .pipeline import commands as pipeline_commands
    from .query import commands as query_commands
    from .segments import commands as segments_commands
    from .train import commands as train_commands
    from .viewer import commands as viewer_commands

    return (
        data_commands,
        gaussians_commands,
        segments_commands,
        train_commands,
        hierarchy_commands,
        query_commands,
        eval_commands,
        pipeline_commands,
        experiments_commands,
        viewer_commands,
    )


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineArgumentParser(
        prog="n2f2",
        description="Nested Neural Feature Fields: hierarchical open-vocabulary queries on 3D Gaussian "
        "Splatting scenes.",
    )
    parser.add_argument("--version", action="version", version=f"n2f2 {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for module in command_modules():
        module.register(subparsers)
    return parser


def _choose_process_kind(argv: list[str]) -> None:
    """The OpenMP wait policy (above) and glibc's large-block thresholds (:mod:`n2f2.heap`) of a
    batch command or of the viewer (which sets its own when its server starts)."""
    command = next((a for a in argv if not a.startswith("-")), None)
    if command in PASSIVE_WAIT_COMMANDS:
        os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    else:
        os.environ.setdefault("GOMP_SPINCOUNT", BATCH_SPIN_COUNT)
        keep_freed_blocks()


# What a command stopped with Ctrl-C keeps, and how to go on from there.
CONTINUE_HINT = {
    **dict.fromkeys(("run", "demo", "run-many"), "; the same command continues where it stopped"),
    **dict.fromkeys(("fit-gaussians", "train"), "; add --resume to continue from the last checkpoint"),
    "segments": "; add --resume to finish the bank (its finished images are kept)",
}


def main(argv: list[str] | None = None) -> int:
    _choose_process_kind(sys.argv[1:] if argv is None else [str(a) for a in argv])
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    import contextlib

    from .io import DISK_ERRNOS, command_outputs

    # A failed command leaves its output folders as they were. A server's files (the viewer's
    # exports) are the user's once written: Ctrl-C, its normal end, must not take them back.
    journal = contextlib.nullcontext() if args.command in SERVER_COMMANDS else command_outputs()
    try:
        with journal:
            result = args.func(args)
    except N2F2Error as e:
        print(f"n2f2 {args.command}: error: {one_line(str(e))}", file=sys.stderr)
        return 2
    except OSError as e:
        if e.errno not in DISK_ERRNOS:
            raise
        where = f"{e.filename}: " if e.filename else ""
        print(f"n2f2 {args.command}: error: {where}{e.strerror or e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"n2f2 {args.command}: interrupted{CONTINUE_HINT.get(args.command, '')}", file=sys.stderr)
        return 130
    return int(result or 0)


def one_line(text: str, limit: int = 400) -> str:
    """An error's text as one console line: newlines folded, long texts shortened."""
    text = " ".join(text.split("\n"))
    return text if len(text) <= limit else text[: limit - 20] + f"... ({len(text)} characters)"


if __name__ == "__main__":
    sys.exit(main())
