"""``n2f2 train``: optimise the nested feature field of a scene (3DGS frozen), and
``n2f2 eval-field``: per-level cosine similarity to the teacher on held-out views (demo scene)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..config import add_config_options, add_preset_option, config_overrides, field_default, stage_job_args
from ..validate import add_device_option, nonneg_int, positive_float


def _preset_summary(name: str) -> str:
    from ..field.model import FieldConfig
    from .config import TrainConfig

    f, t = FieldConfig.preset(name), TrainConfig.preset(name)
    return f"D={f.dim}, {f.plane_resolution}^2x{f.plane_channels} planes, {t.iterations} steps"


def register(subparsers) -> None:
    from ..field.model import FieldConfig
    from .config import TrainConfig

    p = subparsers.add_parser(
        "train",
        help="train the nested feature field (writes field.pt and train_report.json)",
        description="Optimise N2F2's nested feature field on a scene with frozen 3D Gaussians and a "
        "segment bank: TriPlane+MLP at the Gaussian centres, deferred rendering, "
        f"scale-masked projection W, L2 + {TrainConfig.paper().cos_weight:g} cosine loss. Writes DIR/field.pt, "
        "DIR/train_report.json, DIR/checkpoint.pt and DIR/gaussians.ply.",
    )
    p.add_argument("data", metavar="DATA", help="scene folder (COLMAP sparse/0 or nerfstudio transforms.json)")
    p.add_argument("--gaussians", required=True, metavar="PLY", help="fitted 3DGS (gaussians.ply or its folder)")
    p.add_argument("--segments", required=True, metavar="BANK", help="segment bank folder (`n2f2 segments`)")
    p.add_argument("--out", required=True, metavar="DIR", help="run folder")
    add_preset_option(
        p, f"cpu: small field, {_preset_summary('cpu')}; paper: the paper's field, {_preset_summary('paper')}"
    )
    # Every option() field of the two configs (n2f2.config); None keeps the preset's (or the
    # checkpoint's) value.
    add_config_options(p, FieldConfig)
    add_config_options(p, TrainConfig)
    p.add_argument(
        "--train-on-all",
        action="store_true",
        help="also train on the views scene.json lists as test_views (held out by default)",
    )
    p.add_argument("--resume", action="store_true", help="continue from DIR/checkpoint.pt")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace the results already in DIR (field.pt, checkpoint.pt, train_report.json)",
    )
    p.add_argument(
        "--downscale", type=positive_float, default=1.0, help="image downscale factor, as 3DGS -r (default 1)"
    )
    p.add_argument(
        "--skip-missing",
        action="store_true",
        help="drop views whose image file is missing (default: a missing image is an error)",
    )
    seed = field_default(TrainConfig, "seed")
    p.add_argument("--seed", type=nonneg_int, default=seed, help=f"random seed (default {seed})")
    add_device_option(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_train)

    e = subparsers.add_parser(
        "eval-field",
        help="per-level cosine similarity of a trained field to the teacher (demo scene)",
        description="For each hierarchy level (part, object, group) of a scene with ground-truth regions, "
        "the mean cosine similarity between phi(u, s) and the teacher embedding of the "
        "segment covering u, on the held-out views of the run.",
    )
    e.add_argument("run", metavar="RUN", help="run folder of `n2f2 train`")
    e.add_argument("--data", metavar="DATA", default=None, help="scene folder (default: the one the run used)")
    e.add_argument("--segments", metavar="BANK", default=None, help="segment bank (default: the run's)")
    e.add_argument(
        "--views",
        choices=["heldout", "train", "all"],
        default="heldout",
        help="which views to score (default: held-out)",
    )
    e.add_argument("--out", metavar="JSON", default=None, help="write the result here (default RUN/eval_field.json)")
    add_device_option(e)
    e.set_defaults(func=run_eval_field)


def run_train(args: argparse.Namespace) -> int:
    from ..field.model import FieldConfig
    from .config import TrainConfig
    from .stage import TrainJob, run_train

    run_train(
        TrainJob(
            data=Path(args.data),
            gaussians=Path(args.gaussians),
            bank=Path(args.segments),
            out=Path(args.out),
            preset=args.preset,
            field_overrides=config_overrides(args, FieldConfig),
            train_overrides=config_overrides(args, TrainConfig),
            train_on_all=args.train_on_all,
            seed=args.seed,
            **stage_job_args(args),
        )
    )
    return 0


def run_eval_field(args: argparse.Namespace) -> int:
    from ..data import load_scene
    from ..errors import InputError
    from ..field import load_field
    from ..gaussians import read_ply
    from ..io import write_json
    from ..segments import SegmentBank
    from .config import FIELD_NAME
    from .evaluate import evaluate_cosine_by_level
    from .stage import gaussians_path

    run = Path(args.run)
    field, meta = load_field(run / FIELD_NAME, device=args.device)
    data = args.data or meta.get("scene")
    bank_path = args.segments or meta.get("bank")
    if not data or not bank_path:
        raise InputError(run / FIELD_NAME, "the run does not record its scene / bank; pass --data and --segments")
    scene = load_scene(data)
    if scene.ground_truth is None:
        raise InputError(data, "eval-field needs a scene with ground-truth regions (the demo scene)")
    bank = SegmentBank.open(bank_path)
    bank.validate_against(scene)
    if bank.embed_dim != field.embed_dim:
        raise InputError(
            bank_path, f"bank embeddings are {bank.embed_dim}-d but the field was trained for E = {field.embed_dim}"
        )
    gaussians = read_ply(gaussians_path(meta.get("gaussians") or str(run)))
    views = {
        "heldout": meta.get("heldout_views") or [],
        "train": meta.get("train_views") or [],
        "all": list(range(len(scene))),
    }[args.views]
    if not views:
        raise InputError(run / FIELD_NAME, f"the run has no {args.views} views (use --views all)")
    result = evaluate_cosine_by_level(field, gaussians, scene, bank, views, device=args.device)
    result["run"] = str(run)
    write_json(args.out or run / "eval_field.json", result)
    cells = ", ".join(
        f"{k} {v['cosine']:.4f} / {v['region_cosine']:.4f}"
        for k, v in result["levels"].items()
        if v["cosine"] is not None
    )
    print(f"eval-field: mean cosine (pixels / regions) on {len(views)} {args.views} views: {cells}")
    names = list(result["levels"])
    for row in result["per_view"]:
        print(
            f"  view {row['view']:3d}: "
            + ", ".join(f"{n} {row[n]:.4f}" if row[n] is not None else f"{n} n/a" for n in names)
        )
    return 0
