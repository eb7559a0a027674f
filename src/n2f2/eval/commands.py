"""``n2f2 eval``: score a trained run on LangSplat-format labels (LERF-OVS protocol, both box
sizes, mAP, simple vs compound and part / object / group splits, R@K retrieval, per-query deltas
against another run, and with ``--budget`` the loss budget from the teacher to the answers)."""

from __future__ import annotations

import argparse

from ..validate import positive_float


def register(subparsers) -> None:
    from ..query.engine import MODES

    p = subparsers.add_parser(
        "eval",
        help="evaluate a trained run on LangSplat-format labels (loc. accuracy, mIoU, mAP, R@K, deltas)",
        description="Render every labelled view once, answer all of its label categories in one batch per "
        "mode, and score them with LangSplat's LERF-OVS protocol, under LangSplat's exact 30 px "
        "box and under the box scaled to the image width (both are always reported), with the "
        "threshold-free AP of each map against the exact mask (else the label polygons). Writes "
        "OUT/eval.json (every number), OUT/eval.md (tables), OUT/*.png (plots) and float32 "
        "relevancy maps OUT/relevancy/<view>/<query>.npy of the composite mode (for rescoring "
        "with other evaluators; the three level maps [3, H, W] for a 3-level field).",
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="trained run folder (field.pt + gaussians.ply)")
    p.add_argument(
        "--labels",
        required=True,
        metavar="DIR",
        help="label folder of frame_XXXXX.json files (LangSplat / expanded LERF-OVS format)",
    )
    p.add_argument(
        "--mode",
        nargs="+",
        choices=MODES,
        default=None,
        metavar="MODE",
        help=f"query modes to score ({', '.join(MODES)}); default: every mode the field supports "
        "(composite explicit oracle for a nested field, levels oracle for a 3-level one)",
    )
    p.add_argument("--scene", default=None, metavar="DIR", help="scene folder (default: the run's)")
    p.add_argument(
        "--bank", default=None, metavar="DIR", help="segment bank giving the R@K segment pool (default: the run's bank)"
    )
    p.add_argument("--out", default=None, metavar="DIR", help="output folder (default RUN_DIR/eval)")
    p.add_argument(
        "--compare",
        default=None,
        metavar="EVAL_JSON",
        help="another run's eval.json: per-query IoU delta (this run - that run), top/bottom 3",
    )
    p.add_argument(
        "--query-types",
        default=None,
        metavar="JSON",
        help="query types (simple / compound) as queries.json or {query: type} "
        "(default: SCENE/queries.json; otherwise 'unknown')",
    )
    p.add_argument(
        "--skip-missing-frames",
        action="store_true",
        help="skip (and count) labels of frames that are not views of the scene instead of failing",
    )
    p.add_argument(
        "--rescale-labels",
        action="store_true",
        help="scale labels drawn at another resolution to the render size (not LangSplat)",
    )
    p.add_argument(
        "--temperature",
        type=positive_float,
        default=1.0,
        help="composite gamma = softmax(score / T); 1 = paper (default)",
    )
    p.add_argument("--no-relevancy", action="store_true", help="do not write the relevancy .npy files")
    p.add_argument(
        "--budget",
        action="store_true",
        help="also write the loss budget: the same labels scored on the teacher's own per-view features "
        "(the segment bank at 3 levels), on the teacher lifted onto the Gaussians and rendered back "
        "(`lift`, no network), and on the field (oracle scale, composite, explicit); one table of "
        "mIoU, loc., mAP and the part / object / group split in eval.json and eval.md",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace the evaluation already in OUT (eval.json, eval.md, the plots, relevancy/)",
    )
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ..errors import InputError
    from ..io import claim_out_dir, remove_results
    from ..query.engine import QueryConfig
    from .reports import eval_results, mode_summary_lines
    from .runner import EvalConfig, evaluate_run, load_eval, write_eval_outputs

    if not args.temperature > 0:
        raise InputError(None, f"--temperature must be > 0, got {args.temperature}")
    out = Path(args.out) if args.out else Path(args.run_dir) / "eval"
    present = claim_out_dir(out, eval_results(out), force=args.force, resume_flag=None)
    if args.compare is not None:
        if "eval.json" in present and Path(args.compare).resolve() == (out / "eval.json").resolve():
            raise InputError(
                args.compare, "--compare names the eval.json this evaluation replaces: copy it elsewhere first"
            )
        load_eval(args.compare)  # fail on a bad comparison file before any work
    config = EvalConfig(
        modes=tuple(args.mode) if args.mode else None,
        missing_frames="skip" if args.skip_missing_frames else "error",
        rescale_labels=args.rescale_labels,
        progress=not args.quiet,
    )
    query_config = QueryConfig(temperature=args.temperature)
    engine = None
    if args.budget:  # one engine (and text encoder) for the evaluation and the budget
        from ..query.engine import QueryEngine

        engine = QueryEngine.from_run(args.run_dir, device=args.device, scene=args.scene, config=query_config)
        bank = args.bank or engine.meta.get("bank")
        if not bank or not Path(bank).is_dir():  # before any work: the teacher is the segment bank
            raise InputError(
                Path(bank) if bank else Path(args.run_dir),
                "--budget needs the run's segment bank (the teacher): pass --bank DIR",
            )
    result = evaluate_run(
        args.run_dir,
        args.labels,
        scene=args.scene,
        bank=args.bank,
        query_types=args.query_types,
        config=config,
        query_config=query_config,
        device=args.device,
        relevancy_dir=None if args.no_relevancy else out / "relevancy",
        on_ready=lambda: remove_results(out, present),  # --force: the inputs are checked
        engine=engine,
    )
    if args.budget:
        from .budget import loss_budget

        result.budget = loss_budget(
            args.run_dir,
            args.labels,
            scene=args.scene,
            bank=args.bank,
            query_types=args.query_types,
            config=config,
            query_config=query_config,
            device=args.device,
            field_result=result,
            engine=engine,
        )
    write_eval_outputs(result, out, compare=args.compare)
    for line in mode_summary_lines(result):
        print(line)
    if result.budget:
        from .budget import budget_table

        print("loss budget:\n" + budget_table(result.budget))
    for note in result.notes:
        print(f"note: {note}")
    print(f"eval: {result.scores[result.modes[0]]['exact'].num_pairs} pairs in {result.seconds:.1f} s -> {out}")
    return 0
