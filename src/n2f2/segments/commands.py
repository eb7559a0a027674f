"""``n2f2 segments`` and ``n2f2 segments-from-langsplat``: build a scene's segment bank;
``n2f2 segments-export-langsplat``: write a bank as LangSplat ``language_features``.

The LangSplat import is its own command (``segments-from-langsplat``) rather than a sub-action
of ``segments``, because ``segments`` takes the scene folder as its first positional argument
and argparse cannot tell a folder name from a sub-action name.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from ..config import add_config_options, add_preset_option, config_overrides, default_preset, stage_job_args
from ..distributed import add_executor_options
from ..validate import add_device_option, positive_float
from .encoders import ENCODER_NAMES
from .lifting import LiftSettings
from .segmenters import SEGMENTER_NAMES, SEGMENTERS
from .stage import BankJob, run_bank


def segmenter_help() -> str:
    """``--segmenter``'s help, from the registry."""
    return "; ".join(f"{k.name}: {k.description}" for k in SEGMENTERS.values())


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("data", metavar="DATA", help="scene folder (COLMAP sparse/0 or nerfstudio transforms.json)")
    p.add_argument("--out", required=True, metavar="BANK", help="output segment bank folder")
    p.add_argument(
        "--resume",
        action="store_true",
        help="finish the bank in BANK (its images with a record are skipped; settings must match)",
    )
    p.add_argument("--force", action="store_true", help="replace the bank already in BANK")
    p.add_argument(
        "--gaussians",
        metavar="PLY",
        help="fitted 3DGS (gaussians.ply, or the fit-gaussians folder) whose expected depth "
        "lifts segments to 3D; not needed with --depth-source gt",
    )
    p.add_argument(
        "--depth-source",
        choices=["render", "gt"],
        default="render",
        help="render: expected depth of --gaussians (paper, default); gt: the demo scene's exact depth maps",
    )
    add_preset_option(p, "the segment scale measure")
    add_config_options(p, LiftSettings)  # --scale-measure; None keeps the preset's
    p.add_argument(
        "--downscale", type=positive_float, default=1.0, help="image downscale factor, as 3DGS -r (default 1)"
    )
    p.add_argument(
        "--skip-missing",
        action="store_true",
        help="drop views whose image file is missing (default: a missing image is an error)",
    )
    add_device_option(p, " for models and rendering")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "segments",
        help="extract the segment bank: segments, language embeddings, 3D scales",
        description="Segment every image (SAM, Felzenszwalb or the demo scene's ground truth), embed "
        "each segment (CLIP, or ground-truth captions with all-MiniLM-L6-v2 as an offline "
        "stand-in for CLIP), lift it to 3D with the Gaussians' expected depth to measure its "
        "physical scale, and fit the quantile transform of scales. Writes BANK/bank.json and "
        "one record per image; --resume finishes an interrupted bank.",
    )
    _common(p)
    p.add_argument(
        "--segmenter",
        choices=SEGMENTER_NAMES,
        default="sam",
        help=segmenter_help(),
    )
    p.add_argument(
        "--encoder",
        choices=ENCODER_NAMES,
        default="clip",
        help="clip: CLIP image encoder on masked segments (paper, default); captions: ground-truth "
        "captions embedded by all-MiniLM-L6-v2 (offline stand-in, needs --segmenter ground-truth)",
    )
    p.add_argument(
        "--model",
        "--clip-model",
        dest="model",
        metavar="ID",
        default=None,
        help="CLIP model: Hugging Face id or a local folder saved with save_pretrained "
        "(default laion/CLIP-ViT-B-16-laion2B-s34B-b88K)",
    )
    p.add_argument(
        "--sam-model",
        metavar="ID",
        default=None,
        help="SAM or SAM 2 model: Hugging Face id or a local folder saved with save_pretrained (default: "
        + ", ".join(f"{k.default_model_id} for {k.name}" for k in SEGMENTERS.values() if k.default_model_id)
        + ")",
    )
    add_executor_options(p, "image")
    p.set_defaults(func=run_segments)

    q = subparsers.add_parser(
        "segments-from-langsplat",
        help="build the segment bank from LangSplat's language_features",
        description="Import LangSplat's preprocessed segments and CLIP features (<stem>_s.npy, <stem>_f.npy) "
        "as a segment bank, lifting each segment to 3D for its scale, so N2F2 trains without "
        "re-running SAM and CLIP.",
    )
    _common(q)
    q.add_argument(
        "--features",
        metavar="DIR",
        default=None,
        help="LangSplat language_features folder (default DATA/language_features)",
    )
    q.add_argument(
        "--encoder",
        choices=ENCODER_NAMES,
        default=None,
        help="text encoder the features are aligned with: clip (LangSplat's OpenCLIP ViT-B/16 "
        "laion2b_s34b_b88k) or captions (ground-truth captions embedded by all-MiniLM-L6-v2, "
        "the offline stand-in that `n2f2 segments-export-langsplat` exports from a demo bank). "
        "Default: the encoder an n2f2 export recorded in DIR/encoder.json, else clip",
    )
    q.add_argument(
        "--model",
        metavar="ID",
        default=None,
        help="CLIP model id recorded for queries (default laion/CLIP-ViT-B-16-laion2B-s34B-b88K)",
    )
    q.set_defaults(func=run_from_langsplat)

    x = subparsers.add_parser(
        "segments-export-langsplat",
        help="write a segment bank as LangSplat language_features",
        description="Write a segment bank's segments and embeddings in LangSplat's language_features format "
        "(<stem>_s.npy: [4, H, W] global row indices per level default/s/m/l, -1 = none; "
        "<stem>_f.npy: [N, E] embeddings) plus encoder.json naming the text encoder. Each LangSplat "
        "level takes one bank layer (--levels); the demo's ground truth maps to default = object, "
        "s = part, m = object, l = group.",
    )
    x.add_argument("bank", metavar="BANK", help="segment bank folder (`n2f2 segments`)")
    x.add_argument("--out", required=True, metavar="DIR", help="output folder (e.g. SCENE/language_features)")
    x.add_argument(
        "--levels",
        nargs=4,
        metavar=("DEFAULT", "S", "M", "L"),
        default=None,
        help="bank layer (index, or level name such as part / object / group) for each LangSplat "
        "level (default: 1 0 1 2, i.e. object part object group)",
    )
    x.add_argument("--force", action="store_true", help="replace the LangSplat files already in DIR")
    x.add_argument("--quiet", action="store_true", help="no progress bar")
    x.set_defaults(func=run_export_langsplat)


def job_from_args(args: argparse.Namespace, **kw) -> BankJob:
    """The bank job of `segments` or `segments-from-langsplat` flags (``kw``: the rest)."""
    return BankJob(
        data=Path(args.data),
        out=Path(args.out),
        gaussians=None if args.gaussians is None else Path(args.gaussians),
        lift=replace(
            LiftSettings.preset(args.preset or default_preset(args.device)), **config_overrides(args, LiftSettings)
        ),
        model=args.model,
        depth_source=args.depth_source,
        **stage_job_args(args),
        **kw,
    )


def run_segments(args: argparse.Namespace) -> int:
    from ..distributed import executor_from_args

    job = job_from_args(args, segmenter=args.segmenter, encoder=args.encoder, sam_model=args.sam_model)
    executor = executor_from_args(args, gpu=str(args.device).startswith("cuda"))  # Ray missing: fail first
    run_bank(job, executor=executor)
    return 0


def run_from_langsplat(args: argparse.Namespace) -> int:
    features = Path(args.features) if args.features else Path(args.data) / "language_features"
    run_bank(job_from_args(args, encoder=args.encoder, features=features))
    return 0


def run_export_langsplat(args: argparse.Namespace) -> int:
    from .langsplat import DEFAULT_LEVEL_LAYERS, export_langsplat

    report = export_langsplat(
        args.bank, args.out, level_layers=args.levels or DEFAULT_LEVEL_LAYERS, progress=not args.quiet, force=args.force
    )
    lv = ", ".join(f"{k} = layer {v}" for k, v in report["levels"].items())
    print(
        f"segments-export-langsplat: {report['images']} images, {report['rows']} feature rows ({lv}); "
        f"{report['segments_not_exported']} segments in no exported layer -> {report['out']}"
    )
    return 0
