"""``n2f2 eval``: score a trained run on LangSplat-format labels (LERF-OVS protocol, both box
sizes, mAP, simple vs compound and part / object / group splits, R@K retrieval, per-query deltas
against another run, and with ``--budget`` the loss budget from the teacher to the answers);
with ``--protocol 3d|both`` the 3D protocol (:mod:`n2f2.eval.protocol3d`); on labels in the
3D-OVS layout the 3D-OVS protocol (:mod:`n2f2.eval.ovs3d`). ``n2f2 export-ovs3d`` writes a
generated scene in that layout."""

from __future__ import annotations

import argparse

from ..validate import add_device_option, nonneg_int

PROTOCOLS = ("2d", "3d", "both", "3d-ovs")  # --protocol


def register(subparsers) -> None:
    from ..query.commands import add_composite_options, add_render_option
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
        help="label folder of frame_XXXXX.json files (LangSplat / expanded LERF-OVS format), or a scene in the "
        "3D-OVS layout (SCENE or SCENE/segmentations with classes.txt: scored by the 3D-OVS protocol)",
    )
    p.add_argument(
        "--protocol",
        choices=PROTOCOLS,
        default=None,
        help="2d: LangSplat's LERF-OVS protocol on rendered relevancy maps (default for LERF-OVS labels); "
        "3d: Gaussians selected in 3D and rendered into each labelled view (OpenGaussian's protocol: "
        "mIoU, mAcc@0.25, localization); both: the two side by side in one eval.json / eval.md; "
        "3d-ovs: the 3D-OVS protocol (default when --labels is in the 3D-OVS layout)",
    )
    p.add_argument(
        "--ovs-prediction",
        choices=("argmax", "threshold"),
        default="argmax",
        help="3D-OVS: argmax = each pixel takes its most relevant class (3D-OVS, default); threshold = "
        "LangSplat's per-class segmentation rule",
    )
    p.add_argument(
        "--mode",
        nargs="+",
        choices=MODES,
        default=None,
        metavar="MODE",
        help=f"query modes to score ({', '.join(MODES)}); default: every mode the field supports "
        "(composite explicit soft oracle for a nested or flat field, levels oracle for a 3-level one)",
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
    add_composite_options(p)
    add_render_option(p)
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
    add_device_option(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)

    x = subparsers.add_parser(
        "export-ovs3d",
        help="write a generated scene in the 3D-OVS layout (segmentations/classes.txt + per-view class masks)",
        description="Copy a generated scene's images and cameras into OUT (its ground-truth files left out) and "
        "write OUT/segmentations/classes.txt and OUT/segmentations/<NN>/<class>.png: the regions of one "
        "level of regions.json as classes, their exact region-map masks (255 = class) in each listed view. "
        "`n2f2 eval RUN --labels OUT` then scores a run with the 3D-OVS protocol.",
    )
    x.add_argument("scene", metavar="SCENE", help="generated scene folder (regions/ + regions.json)")
    x.add_argument("out", metavar="OUT", help="output folder")
    x.add_argument(
        "--level",
        default="object",
        help="the regions.json level whose regions become the classes (part, object, group; default object)",
    )
    x.add_argument(
        "--views",
        nargs="+",
        type=nonneg_int,
        default=None,
        metavar="I",
        help="view indices to write masks for (default: the scene's labelled views, else all)",
    )
    x.add_argument("--force", action="store_true", help="replace what OUT already holds")
    x.set_defaults(func=run_export)


def run_export(args: argparse.Namespace) -> int:
    from .ovs3d import export_ovs3d

    info = export_ovs3d(args.scene, args.out, level=args.level, views=args.views, force=args.force)
    print(
        f"export-ovs3d: {len(info['classes'])} classes ({info['level']} level), {len(info['views'])} views "
        f"-> {args.out}/segmentations"
    )
    return 0


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from ..errors import InputError
    from ..io import claim_out_dir, remove_results
    from ..query.commands import composite_config
    from ..query.engine import QueryConfig, QueryEngine
    from .ovs3d import ovs3d_labels_path
    from .protocol3d import Protocol3dConfig, evaluate_protocol3d, modes_3d
    from .reports import eval_results, mode_summary_lines, protocol3d_summary_lines, write_eval_outputs
    from .runner import EvalConfig, evaluate_run, load_eval

    composite = composite_config(args)
    ovs_labels = ovs3d_labels_path(args.labels)
    protocol = args.protocol or ("3d-ovs" if ovs_labels is not None else "2d")
    if ovs_labels is not None and protocol != "3d-ovs":
        raise InputError(args.labels, f"labels in the 3D-OVS layout are scored by --protocol 3d-ovs, not {protocol}")
    unused = {
        "3d": ("--compare", "--budget", "--query-types", "--bank"),
        "3d-ovs": ("--compare", "--budget", "--query-types", "--bank", "--skip-missing-frames", "--rescale-labels"),
    }.get(protocol, ())
    given = {
        "--compare": args.compare is not None,
        "--budget": args.budget,
        "--query-types": args.query_types is not None,
        "--bank": args.bank is not None,
        "--skip-missing-frames": args.skip_missing_frames,
        "--rescale-labels": args.rescale_labels,
    }
    refused = [flag for flag in unused if given[flag]]
    if refused:
        raise InputError(None, f"{', '.join(refused)} do(es) not apply to --protocol {protocol}")
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
    config3d = Protocol3dConfig(
        missing_frames=config.missing_frames, rescale_labels=config.rescale_labels, progress=config.progress
    )
    query_config = QueryConfig(render=args.render, **composite)
    engine = None
    if args.budget or protocol != "2d":  # one engine (and text encoder) for every protocol and the budget
        engine = QueryEngine.from_run(args.run_dir, device=args.device, scene=args.scene, config=query_config)
    if protocol == "3d-ovs":
        return _run_ovs3d(args, engine, out, lambda: remove_results(out, present))
    if protocol in ("3d", "both"):
        assert engine is not None  # built above for every protocol but 2d
        modes_3d(engine, args.mode)  # before any work: the 3D protocol has no oracle mode
    if protocol == "3d":
        from ..data.labels import read_label_dir
        from .protocol3d import write_protocol3d_outputs

        assert engine is not None
        res = evaluate_protocol3d(
            engine,
            read_label_dir(args.labels),
            modes=args.mode,
            config=config3d,
            label_dir=args.labels,
            on_ready=lambda: remove_results(out, present),
        )
        write_protocol3d_outputs(res, out)
        for line in protocol3d_summary_lines(res.to_dict()):
            print(line)
        for note in res.notes:
            print(f"note: {note}")
        print(f"eval: {res.scores[res.modes[0]].num_pairs} pairs (3D protocol) in {res.seconds:.1f} s -> {out}")
        return 0
    if args.budget:
        assert engine is not None  # opened above for the budget
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
    if protocol == "both":
        from ..data.labels import read_label_dir

        assert engine is not None
        result.protocol3d = evaluate_protocol3d(
            engine, read_label_dir(args.labels), modes=result.modes, config=config3d, label_dir=args.labels
        ).to_dict()
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
    if result.protocol3d:
        for line in protocol3d_summary_lines(result.protocol3d):
            print(line)
    if result.budget:
        from .budget import budget_table

        print("loss budget:\n" + budget_table(result.budget))
    for note in result.notes:
        print(f"note: {note}")
    print(f"eval: {result.scores[result.modes[0]]['exact'].num_pairs} pairs in {result.seconds:.1f} s -> {out}")
    return 0


def _run_ovs3d(args: argparse.Namespace, engine, out, on_ready) -> int:
    """``n2f2 eval`` on labels in the 3D-OVS layout."""
    from .ovs3d import evaluate_run_ovs3d, write_ovs3d_outputs
    from .reports import ovs3d_summary_lines

    data = evaluate_run_ovs3d(
        engine, args.labels, modes=args.mode, prediction=args.ovs_prediction, progress=not args.quiet, on_ready=on_ready
    )
    write_ovs3d_outputs(data, out)
    for line in ovs3d_summary_lines(data):
        print(line)
    for note in data["notes"]:
        print(f"note: {note}")
    print(
        f"eval: 3D-OVS, {len(data['views'])} views x {len(data['classes'])} classes in {data['seconds']:.1f} s -> {out}"
    )
    return 0
