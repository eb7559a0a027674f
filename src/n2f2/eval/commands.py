"""``n2f2 eval``: score a trained run on LangSplat-format labels (LERF-OVS protocol, both box
sizes, mAP, simple vs compound and part / object / group splits, R@K retrieval, per-query deltas
against another run, and with ``--budget`` the loss budget from the teacher to the answers);
with ``--protocol 3d|both`` the 3D protocol (:mod:`n2f2.eval.protocol3d`); on labels in the
3D-OVS layout the 3D-OVS protocol (:mod:`n2f2.eval.ovs3d`). ``n2f2 export-ovs3d`` writes a
generated scene in that layout."""

from __future__ import annotations

import argparse

from ..config import add_config_options
from ..validate import add_device_option, nonneg_int
from .protocols import PROTOCOLS


def register(subparsers) -> None:
    from ..query.commands import add_composite_options, add_decomposition_option, add_render_option
    from .runner import EvalConfig

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
        choices=list(PROTOCOLS),
        default=None,
        help="; ".join(f"{p.name}: {p.description}" for p in PROTOCOLS.values()),
    )
    p.add_argument(
        "--ovs-prediction",
        choices=("argmax", "threshold"),
        default="argmax",
        help="3D-OVS: argmax = each pixel takes its most relevant class (3D-OVS, default); threshold = "
        "LangSplat's per-class segmentation rule",
    )
    add_config_options(p, EvalConfig, {"modes": "mode"})  # None: EvalConfig's (every mode the field has)
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
    add_decomposition_option(p)
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
    register_eval_hierarchy(subparsers)


def register_eval_hierarchy(subparsers) -> None:
    """``n2f2 eval-hierarchy``: a decomposition of a run's Gaussians against ground-truth regions."""
    from .hierarchy import HierarchyEvalSettings

    h = subparsers.add_parser(
        "eval-hierarchy",
        help="score a `n2f2 decompose` hierarchy against a generated scene's part / object / group regions",
        description="For every labelled view of SCENE with DECOMP/views/<stem>/levels.npy: the best IoU of each "
        "ground-truth region (part, object, group) with any node at any level of the hierarchy, and with any "
        "segment of a 2D-only baseline (multi-scale Felzenszwalb on the image); the cross-view consistency of "
        "the best nodes and the share of nodes not nested in their parent (tree.json, gaussian_nodes.npy). "
        "With --segments BANK in place of --labels, the regions are the segments the field was trained on "
        "(for captures without ground truth). "
        "Writes OUT/eval_hierarchy.json (every number), OUT/eval_hierarchy.md and OUT/eval_hierarchy.png.",
    )
    h.add_argument("run_dir", metavar="RUN", help="the trained run that was decomposed")
    h.add_argument("decomp", metavar="DECOMP", help="the `n2f2 decompose RUN --out DECOMP` folder (tree.json, ...)")
    truth = h.add_mutually_exclusive_group(required=True)
    truth.add_argument(
        "--labels", default=None, metavar="SCENE", help="generated scene with ground truth (regions/, regions.json)"
    )
    truth.add_argument(
        "--segments",
        default=None,
        metavar="BANK",
        help="instead of ground truth, the segment bank the field was trained on (`n2f2 segments`; its "
        "segments by scale: small, medium, large): for captures without ground truth",
    )
    h.add_argument("--out", default=None, metavar="DIR", help="output folder (default DECOMP/eval_hierarchy)")
    add_config_options(h, HierarchyEvalSettings, field_defaults=True)
    h.add_argument("--force", action="store_true", help="replace the evaluation already in OUT")
    h.set_defaults(func=run_eval_hierarchy)


def run_eval_hierarchy(args: argparse.Namespace) -> int:
    from .hierarchy import HierarchyEvalSettings, evaluate_hierarchy

    settings = HierarchyEvalSettings(min_pixels=args.min_pixels, baseline_scales=tuple(args.baseline_scales))
    evaluate_hierarchy(
        args.run_dir,
        args.decomp,
        args.labels,
        segments=args.segments,
        out=args.out,
        settings=settings,
        force=args.force,
    )
    return 0


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

    from ..query.commands import composite_config
    from ..query.engine import QueryConfig
    from .stage import EvalJob, run_eval

    def path(value):
        return None if value is None else Path(value)

    run_eval(
        EvalJob(
            run_dir=Path(args.run_dir),
            labels=Path(args.labels),
            out=path(args.out),
            protocol=args.protocol,
            ovs_prediction=args.ovs_prediction,
            modes=args.mode,
            scene=path(args.scene),
            bank=path(args.bank),
            compare=path(args.compare),
            query_types=path(args.query_types),
            skip_missing_frames=args.skip_missing_frames,
            rescale_labels=args.rescale_labels,
            query_config=QueryConfig(render=args.render, decomposition=args.decomposition, **composite_config(args)),
            relevancy=not args.no_relevancy,
            budget=args.budget,
            force=args.force,
            device=args.device,
            progress=not args.quiet,
        )
    )
    return 0
