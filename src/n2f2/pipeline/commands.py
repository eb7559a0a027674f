"""``n2f2 run``, ``n2f2 run-many``, ``n2f2 demo`` and ``n2f2 doctor``: the command-line side of the
pipeline (options, checks, printing); the work is in :mod:`.run`, :mod:`.many` and :mod:`.doctor`."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..config import add_config_options, add_preset_option, config_overrides
from ..distributed import add_executor_options
from ..errors import InputError
from ..field.model import FieldConfig
from ..gaussians.fit import FitConfig
from ..segments.encoders import ENCODER_NAMES
from ..segments.lifting import LiftSettings
from ..segments.segmenters import SEGMENTER_NAMES
from ..train.config import TrainConfig
from ..validate import add_device_option, nonneg_int, positive_float, positive_int
from .presets import PRESETS
from .run import DEFAULT_MODES, DemoScene, RunOptions

# The stage settings `run` can change: {Preset attribute: (its config class, {field: flag})}.
# Each flag's help, type and choices are the field's own (n2f2.config.option), followed by its
# value under every preset.
STAGE_FLAGS: dict[str, tuple[type, dict[str, str]]] = {
    "fit": (FitConfig, {"steps": "fit-steps"}),
    "train": (TrainConfig, {"iterations": "train-steps"}),
    "field": (FieldConfig, {"dim": "dim", "variant": "variant"}),
    "lift": (LiftSettings, {"scale_measure": "scale-measure"}),
}


def _add_stage_options(p: argparse.ArgumentParser, stage: str) -> None:
    cls, flags = STAGE_FLAGS[stage]
    add_config_options(p, cls, flags, presets={name: getattr(make(), stage) for name, make in PRESETS.items()})


def _add_run_options(p: argparse.ArgumentParser, per_scene_inputs: bool = True) -> None:
    """The options of ``run``; ``per_scene_inputs=False`` leaves out those naming one scene's
    files (--gaussians, --langsplat-features, --labels), for ``run-many``."""
    if per_scene_inputs:
        p.add_argument("--gaussians", metavar="PLY", default=None, help="use these Gaussians instead of fitting")
    p.add_argument(
        "--segmenter",
        choices=SEGMENTER_NAMES,
        default=None,
        help="segmenter (default: ground-truth on the demo scene, else sam)",
    )
    p.add_argument(
        "--encoder",
        choices=ENCODER_NAMES,
        default=None,
        help="encoder (default: captions = ground-truth captions embedded by all-MiniLM-L6-v2, an "
        "offline stand-in for CLIP, with the demo scene's ground-truth segmenter; else clip). "
        "With --langsplat-features: "
        "the text encoder the features are aligned with (default: the one an n2f2 export "
        "recorded in DIR/encoder.json, else clip)",
    )
    p.add_argument("--model", "--clip-model", dest="model", metavar="ID", default=None, help="CLIP model id or folder")
    p.add_argument(
        "--sam-model",
        metavar="ID",
        default=None,
        help="SAM or SAM 2 model (--segmenter sam|sam2): Hugging Face id or a local folder saved with save_pretrained",
    )
    if per_scene_inputs:
        p.add_argument(
            "--langsplat-features",
            metavar="DIR",
            default=None,
            help="LangSplat language_features folder (<stem>_s.npy, <stem>_f.npy): import instead of segmenting",
        )
        p.add_argument(
            "--labels", metavar="DIR", default=None, help="LangSplat-format labels (default: DATA/label when it exists)"
        )
    add_preset_option(p, "settings of every stage, n2f2.pipeline.presets")
    for stage in ("fit", "train", "field"):  # None: the --preset's value
        _add_stage_options(p, stage)
    p.add_argument(
        "--depth-source",
        choices=["render", "gt"],
        default="render",
        help="lift segments with the Gaussians' rendered depth (default) or the demo scene's exact depth",
    )
    _add_stage_options(p, "lift")
    p.add_argument(
        "--modes", nargs="+", default=list(DEFAULT_MODES), help=f"evaluation modes (default: {' '.join(DEFAULT_MODES)})"
    )
    p.add_argument(
        "--downscale", type=positive_float, default=1.0, help="image downscale factor, as 3DGS -r (default %(default)s)"
    )
    p.add_argument(
        "--skip-missing",
        action="store_true",
        help="drop views whose image file is missing (default: a missing image is an error)",
    )
    add_device_option(p)
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _run_options(args: argparse.Namespace, data: Path, out: Path) -> RunOptions:
    given = {stage: config_overrides(args, cls, flags) for stage, (cls, flags) in STAGE_FLAGS.items()}
    for stage, over in given.items():
        for name, value in over.items():
            if isinstance(value, int) and value <= 0:
                raise InputError(None, f"--{STAGE_FLAGS[stage][1][name]} must be > 0, got {value}")
    return RunOptions(
        data=data,
        out=out,
        gaussians=Path(args.gaussians) if args.gaussians else None,
        segmenter=args.segmenter,
        encoder=args.encoder,
        model=args.model,
        sam_model=args.sam_model,
        langsplat_features=Path(args.langsplat_features) if args.langsplat_features else None,
        labels=Path(args.labels) if args.labels else None,
        preset=args.preset,
        fit_steps=given["fit"].get("steps"),
        train_steps=given["train"].get("iterations"),
        dim=given["field"].get("dim"),
        variant=given["field"].get("variant"),
        depth_source=args.depth_source,
        scale_measure=given["lift"].get("scale_measure"),
        downscale=args.downscale,
        skip_missing=args.skip_missing,
        modes=tuple(args.modes),
        device=args.device,
        quiet=args.quiet,
    )


def _cmd_run(args: argparse.Namespace) -> int:
    from .run import run_pipeline

    start = time.perf_counter()
    result = run_pipeline(_run_options(args, Path(args.data), Path(args.out)))
    print(
        f"run: {result['run_dir']} in {time.perf_counter() - start:.1f} s"
        + (f"; evaluation: {result['eval']}" if result["eval"] else "")
    )
    return 0


def _cmd_doctor(args: argparse.Namespace) -> int:
    from .doctor import run_doctor

    out = Path(args.out) if args.out else None
    return run_doctor(_run_options(args, Path(args.data), out or Path(".")), out_given=out is not None)


def _cmd_run_many(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from ..distributed import executor_from_args
    from .many import SUMMARY_NAME, run_many

    out = Path(args.out)
    scenes = [Path(d) for d in args.data]
    names = [d.resolve().name for d in scenes]
    for name in sorted(set(names)):
        same = [str(d) for d, n in zip(scenes, names) if n == name]
        if len(same) > 1:
            raise InputError(
                None,
                f"scenes {', '.join(same)} share the folder name {name!r}, and each scene's run "
                f"goes to {out}/<scene folder name>",
            )
    executor = executor_from_args(args, gpu=str(args.device).startswith("cuda"))
    opts = [_run_options(args, d, out / n) for d, n in zip(scenes, names)]
    if executor.name == "ray":  # stage progress bars do not survive Ray's log streaming
        device = "cuda" if str(args.device).startswith("cuda") else args.device  # the GPU Ray gives the task
        opts = [replace(o, quiet=True, device=device) for o in opts]
    summary = run_many(opts, out, executor, progress=not args.quiet)
    print((out / f"{SUMMARY_NAME}.md").read_text())
    failed = [r["scene"] for r in summary["scenes"] if r["status"] != "ok"]
    if failed:
        raise InputError(
            None,
            f"{len(failed)} of {len(scenes)} scenes failed: {', '.join(failed)} (details in {out / SUMMARY_NAME}.md)",
        )
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    import torch

    from .run import demo_queries, demo_scene, run_pipeline

    out = Path(args.out)
    start = time.perf_counter()
    spec = DemoScene(views=args.views, width=args.width, height=args.height, seed=args.seed, layout=args.layout)
    compiling = not args.scene_only and args.device == "cpu"
    threads = torch.get_num_threads()
    if compiling:  # the rasterizer compiles while the scene is made
        from ..render.numba_backend import compile_in_background
        from .run import BACKGROUND_KERNELS

        compile_in_background(**BACKGROUND_KERNELS)
        # The scene renders as fast on one thread (17.8 s against 17.6 on two): the compile,
        # which the first fit step waits for, gets the other core.
        torch.set_num_threads(1)
    try:
        scene_dir = demo_scene(out, spec, progress=not args.quiet)
    finally:
        torch.set_num_threads(threads)
    print(f"demo scene: {scene_dir}\ncontact sheet: {out / 'contact_sheet.png'}")
    if args.scene_only:
        return 0
    result = run_pipeline(_run_options(args, scene_dir, out / "run"))
    queries = demo_queries(out, scene_dir, out / "run", args.layout, device=args.device, progress=not args.quiet)
    if result["eval"]:
        md = Path(result["eval"]).with_suffix(".md")
        if md.is_file():
            print(md.read_text())
    print(f"queries: {queries}")
    print(f"demo finished in {time.perf_counter() - start:.1f} s")
    return 0


def register(subparsers) -> None:
    scene = DemoScene()
    p = subparsers.add_parser(
        "demo",
        help="generate the built-in demo scene and run the whole pipeline on it",
        description="Generate a built-in synthetic scene (--layout: a tabletop or a lounge; exact ground truth "
        "at part, object and group level), then fit Gaussians, build the segment bank (ground-truth "
        "segments; captions embedded by all-MiniLM-L6-v2, an offline stand-in for CLIP), train the nested field, "
        "evaluate with LangSplat's protocol, and write a few relevancy PNGs.",
    )
    p.add_argument("--out", default="demo_out", help="output folder (default: %(default)s)")
    p.add_argument("--views", type=positive_int, default=scene.views, help="number of views (default: %(default)s)")
    p.add_argument("--width", type=positive_int, default=scene.width, help="image width (default: %(default)s)")
    p.add_argument("--height", type=positive_int, default=scene.height, help="image height (default: %(default)s)")
    p.add_argument("--seed", type=nonneg_int, default=scene.seed, help="random seed (default: %(default)s)")
    p.add_argument(
        "--layout",
        choices=["tabletop", "lounge"],
        default=scene.layout,
        help="scene layout: tabletop (round table with a tea set and snacks, 6 x 6 m room; every "
        "preset was tuned on it) or lounge (sofa, floor lamp and a coffee table with small "
        "objects in a 14 x 11 m room, on a partial arc with close views). Default: %(default)s",
    )
    p.add_argument("--scene-only", action="store_true", help="only generate the scene and its contact sheet")
    _add_run_options(p)
    p.set_defaults(func=_cmd_demo)

    r = subparsers.add_parser(
        "run",
        help="run every stage on a scene: fit, segments, train, eval (each cached)",
        description="Fit Gaussians (or --gaussians), build the segment bank (or --langsplat-features), train "
        "the nested field, and evaluate when labels exist. Each stage is skipped when its inputs "
        "are unchanged (RUN/stages.json).",
    )
    r.add_argument(
        "data",
        metavar="DATA",
        help="scene folder (COLMAP or nerfstudio), or a folder of photos, posed first by `n2f2 sfm` into DIR/sfm",
    )
    r.add_argument("--out", required=True, metavar="DIR", help="run folder")
    _add_run_options(r)
    r.set_defaults(func=_cmd_run)

    d = subparsers.add_parser(
        "doctor",
        help="check what `run` needs (scene, models, machine, output folder) and estimate each stage's time",
        description="Print, one line each, what `n2f2 run DATA` with the same options would check and expect, "
        "running and writing nothing: the scene's size, every model the stages load (found, and where, or "
        "the command that gets it), the CPU, torch's threads and CUDA, the output folder (--out; its "
        "up-to-date stages are left out, as run skips them), and the expected time of each stage from the "
        "scene's size and the machine's measured speed. Exit status 0 when everything needed is present, "
        "2 otherwise.",
    )
    d.add_argument("data", metavar="DATA", help="scene folder or folder of photos, as for `run`")
    d.add_argument("--out", metavar="DIR", default=None, help="the run folder (checked, not created)")
    _add_run_options(d)
    d.set_defaults(func=_cmd_doctor)

    m = subparsers.add_parser(
        "run-many",
        help="`run` on several scenes, one task per scene (serially or on Ray), and a summary table",
        description="Run every stage (as `n2f2 run`, with the same stage cache) on each scene into "
        "DIR/<scene folder name>/, one task per scene: serially, or as Ray tasks on this machine "
        "or a cluster (docs/distributed.md). A scene failing on bad input is reported and the "
        "others go on; then DIR/summary.md and DIR/summary.json give each scene's mIoU per mode, "
        "time per stage and status, and the command exits 2 if any scene failed.",
    )
    m.add_argument("data", nargs="+", metavar="SCENE", help="scene folders (COLMAP or nerfstudio) or photo folders")
    m.add_argument(
        "--out", required=True, metavar="DIR", help="folder of the runs (DIR/<scene folder name>/) and the summary"
    )
    _add_run_options(m, per_scene_inputs=False)
    add_executor_options(m, "scene")
    m.set_defaults(func=_cmd_run_many, gaussians=None, langsplat_features=None, labels=None)
