"""``n2f2 demo`` and ``n2f2 run``: the stages in data-flow order, each cached on its inputs;
``n2f2 run-many``: ``run`` on several scenes, one task each (serially or on Ray), and a summary.

A stage is skipped when its recorded key (a hash of its inputs' content and its settings)
matches the one in ``RUN/stages.json`` and its outputs still exist.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from .distributed import add_executor_options
from .errors import InputError
from .io import write_json
from .segments.lifting import SCALE_MEASURES
from .validate import nonneg_int, positive_float, positive_int

STAGES_FILE = "stages.json"


# ----------------------------------------------------------------------------- caching
def file_digest(path: Path, _chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(_chunk):
            h.update(block)
    return h.hexdigest()


def tree_digest(root: Path, patterns: tuple[str, ...] = ("**/*",)) -> str:
    """Content hash of every file under ``root`` matching ``patterns`` (names and bytes)."""
    h = hashlib.sha256()
    files = sorted({p for pat in patterns for p in root.glob(pat) if p.is_file()})
    for p in files:
        h.update(str(p.relative_to(root)).encode())
        h.update(file_digest(p).encode())
    return h.hexdigest()


def stage_key(**inputs) -> str:
    return hashlib.sha256(json.dumps(inputs, sort_keys=True, default=str).encode()).hexdigest()[:16]


@dataclass
class StageCache:
    run_dir: Path
    records: dict = field(default_factory=dict)
    ran: list = field(default_factory=list)  # stages run (not skipped) by this process

    @classmethod
    def open(cls, run_dir: Path) -> "StageCache":
        path = run_dir / STAGES_FILE
        records = json.loads(path.read_text()) if path.is_file() else {}
        return cls(run_dir, records)

    def run(self, name: str, key: str, outputs: list[Path], fn: Callable[[], None], log=print) -> bool:
        """Run ``fn`` unless stage ``name`` already ran with ``key`` and its outputs exist.
        Returns True when the stage ran."""
        rec = self.records.get(name)
        if rec and rec.get("key") == key and all(p.exists() for p in outputs):
            log(f"[{name}] up to date (key {key}), skipped")
            return False
        log(f"[{name}] running")
        start = time.perf_counter()
        fn()
        self.records[name] = {"key": key, "seconds": round(time.perf_counter() - start, 2),
                              "outputs": [str(p.relative_to(self.run_dir)) for p in outputs]}
        write_json(self.run_dir / STAGES_FILE, self.records)
        self.ran.append(name)
        log(f"[{name}] done in {self.records[name]['seconds']:.1f} s")
        return True


# ----------------------------------------------------------------------------- the pipeline
def _cli(argv: list[str]) -> None:
    """Run one stage through its own CLI command, so ``run`` does exactly what the stage
    commands do (same options, same validation, same outputs)."""
    from .cli import build_parser

    args = build_parser().parse_args([str(a) for a in argv])
    rc = args.func(args)
    if rc:
        raise InputError(None, f"stage `n2f2 {argv[0]}` failed (exit {rc})")


def scene_digest(scene_dir: Path) -> str:
    """What the fitted Gaussians depend on: poses/intrinsics files and the images."""
    return tree_digest(scene_dir, ("transforms.json", "sparse/**/*", "images/*", "*.ply"))


@dataclass
class RunOptions:
    """Settings of ``n2f2 run``; ``None`` means the default that :func:`resolve_defaults`
    picks from the scene (see there)."""

    data: Path
    out: Path
    gaussians: Path | None = None
    segmenter: str | None = None
    encoder: str | None = None
    model: str | None = None
    langsplat_features: Path | None = None
    labels: Path | None = None
    preset: str = "cpu"
    fit_steps: int | None = None
    train_steps: int | None = None
    dim: int | None = None  # feature-field dims D (None: the preset's)
    variant: str | None = None
    depth_source: str = "render"
    # Segment scale measure (LiftSettings.scale_measure); None: the preset's ("extent" for cpu,
    # "eigenvalue" -- the paper's -- for paper).
    scale_measure: str | None = None
    downscale: float = 1.0
    skip_missing: bool = False  # drop views whose image is missing (every stage drops the same ones)
    modes: tuple[str, ...] = ("composite", "explicit", "oracle")
    device: str = "cpu"
    quiet: bool = False


def is_demo_scene(data: Path) -> bool:
    """A scene with the built-in demo's ground truth (regions with captions, exact depth)."""
    return (Path(data) / "regions.json").is_file()


def resolve_defaults(opt: RunOptions) -> RunOptions:
    """Fill in the scene-dependent defaults:

    * segmenter: ``ground-truth`` on a demo scene, else ``sam`` (the paper's);
    * scale measure: ``eigenvalue`` (the paper's) with the paper preset, else ``extent``;
    * encoder: with ``langsplat_features``, the encoder an n2f2 export recorded beside them
      (``encoder.json``), else ``clip`` (LangSplat's own features are CLIP); otherwise
      ``captions`` (the offline MiniLM stand-in) on a demo scene, else ``clip``."""
    from dataclasses import replace

    demo = is_demo_scene(Path(opt.data))
    segmenter = opt.segmenter or ("ground-truth" if demo else "sam")
    encoder = opt.encoder
    if encoder is None and opt.langsplat_features is not None:
        from .segments.langsplat import recorded_encoder

        feats = Path(opt.langsplat_features)
        recorded = recorded_encoder(feats) if feats.is_dir() else None
        encoder = recorded["name"] if recorded else "clip"
    if encoder is None:
        encoder = "captions" if demo else "clip"
    scale_measure = opt.scale_measure or ("eigenvalue" if opt.preset == "paper" else "extent")
    return replace(opt, segmenter=segmenter, encoder=encoder, scale_measure=scale_measure)


def run_pipeline(opt: RunOptions, log=print) -> dict:
    """Fit Gaussians -> segment bank -> nested field -> evaluation (when labels exist).
    Returns ``{"stages": ..., "run_dir": ..., "eval": path or None}``.

    Works on any COLMAP or nerfstudio scene: without ground truth the segments are lifted with
    the fitted Gaussians' rendered depth (``depth_source="render"``, the default), and with
    ``langsplat_features`` the bank is imported from LangSplat-format files instead of
    segmenting. Evaluation runs on ``labels`` (default ``DATA/label``) when they exist; query
    types (simple / compound) come from ``DATA/queries.json`` when the scene has one."""
    opt = resolve_defaults(opt)
    data, out = Path(opt.data), Path(opt.out)
    if not data.is_dir():
        raise InputError(data, "scene folder does not exist")
    if opt.depth_source == "gt" and not (is_demo_scene(data) and (data / "depth").is_dir()):
        raise InputError(data / "depth", "--depth-source gt needs the exact depth maps of the demo scene "
                         "(depth/*.npy and regions.json); use --depth-source render")
    if opt.langsplat_features is not None and not Path(opt.langsplat_features).is_dir():
        raise InputError(opt.langsplat_features, "LangSplat features folder does not exist")
    if opt.labels is not None and not Path(opt.labels).is_dir():
        raise InputError(opt.labels, "labels folder does not exist")
    out.mkdir(parents=True, exist_ok=True)
    cache = StageCache.open(out)
    quiet = ["--quiet"] if opt.quiet else []
    common = ["--downscale", opt.downscale, "--device", opt.device] + (["--skip-missing"] if opt.skip_missing else [])
    from .data.sfm import posed_scene_path

    data = posed_scene_path(data, out / "sfm", progress=not opt.quiet, log=log)  # photos: pose them first
    sdig = scene_digest(data)

    # 1. Gaussians: fitted here, or given.
    if opt.gaussians is not None:
        ply = Path(opt.gaussians)
        if ply.is_dir():
            ply = ply / "gaussians.ply"
        if not ply.is_file():
            raise InputError(ply, "Gaussians file does not exist")
    else:
        fit_dir = out / "gaussians"
        ply = fit_dir / "gaussians.ply"
        fit_args = ["--preset", opt.preset] + (["--steps", opt.fit_steps] if opt.fit_steps else [])
        cache.run("fit-gaussians", stage_key(scene=sdig, args=fit_args, downscale=opt.downscale),
                  [ply], lambda: _cli(["fit-gaussians", data, "--out", fit_dir, *fit_args, *common, *quiet,
                                       "--force"]), log)  # inputs changed: replace an older fit
    gdig = file_digest(ply)

    # 2. Segment bank.
    bank = out / "bank"
    if opt.langsplat_features is not None:
        feats = Path(opt.langsplat_features)
        seg_args = ["segments-from-langsplat", data, "--features", feats, "--encoder", opt.encoder,
                    "--scale-measure", opt.scale_measure]
        seg_key = stage_key(scene=sdig, gaussians=gdig, features=tree_digest(feats), args=seg_args[3:],
                            depth=opt.depth_source, model=opt.model)
    else:
        seg_args = ["segments", data, "--segmenter", opt.segmenter, "--encoder", opt.encoder,
                    "--scale-measure", opt.scale_measure]
        seg_key = stage_key(scene=sdig, gaussians=gdig, args=seg_args[2:], depth=opt.depth_source, model=opt.model)
    seg_args += ["--out", bank, "--gaussians", ply, "--depth-source", opt.depth_source, *common, *quiet]
    if opt.model:
        seg_args += ["--model", opt.model]

    def build_bank() -> None:
        import shutil

        if bank.exists():  # inputs changed: a resumed extraction would mix old and new records
            shutil.rmtree(bank)
        _cli(seg_args)

    cache.run("segments", seg_key, [bank / "bank.json"], build_bank, log)

    # 3. Nested feature field.
    train_args = ["--preset", opt.preset]
    if opt.train_steps:
        train_args += ["--iterations", opt.train_steps]
    if opt.dim:
        train_args += ["--dim", opt.dim]
    if opt.variant:
        train_args += ["--variant", opt.variant]

    def train() -> None:
        for stale in ("checkpoint.pt", "field.pt"):  # inputs changed: start from scratch
            (out / stale).unlink(missing_ok=True)
        _cli(["train", data, "--gaussians", ply, "--segments", bank, "--out", out, *train_args,
              *common, *quiet, "--force"])

    cache.run("train", stage_key(scene=sdig, gaussians=gdig, bank=file_digest(bank / "bank.json"), args=train_args),
              [out / "field.pt"], train, log)

    # 4. Evaluation, when labels exist.
    labels = Path(opt.labels) if opt.labels else (data / "label" if (data / "label").is_dir() else None)
    eval_json = None
    if labels is not None:
        eval_dir = out / "eval"
        eval_json = eval_dir / "eval.json"
        cache.run("eval", stage_key(field=file_digest(out / "field.pt"), labels=tree_digest(labels),
                                    modes=list(opt.modes)),
                  [eval_json],
                  lambda: _cli(["eval", out, "--labels", labels, "--scene", data, "--bank", bank,
                                "--out", eval_dir, "--mode", *opt.modes, "--device", opt.device, *quiet,
                                "--force"]), log)  # inputs changed: replace an older evaluation
    return {"run_dir": str(out), "stages": cache.records, "ran": list(cache.ran),
            "eval": None if eval_json is None else str(eval_json)}


# ----------------------------------------------------------------------------- commands
def _add_run_options(p: argparse.ArgumentParser, per_scene_inputs: bool = True) -> None:
    """The options of ``run``; ``per_scene_inputs=False`` leaves out those naming one scene's
    files (--gaussians, --langsplat-features, --labels), for ``run-many``."""
    if per_scene_inputs:
        p.add_argument("--gaussians", metavar="PLY", default=None, help="use these Gaussians instead of fitting")
    p.add_argument("--segmenter", choices=["sam", "classical", "ground-truth"], default=None,
                   help="segmenter (default: ground-truth on the demo scene, else sam)")
    p.add_argument("--encoder", choices=["clip", "captions"], default=None,
                   help="encoder (default: captions = ground-truth captions embedded by all-MiniLM-L6-v2, an "
                        "offline stand-in for CLIP, on the demo scene; else clip). With --langsplat-features: "
                        "the text encoder the features are aligned with (default: the one an n2f2 export "
                        "recorded in DIR/encoder.json, else clip)")
    p.add_argument("--model", metavar="ID", default=None, help="CLIP model id or folder")
    if per_scene_inputs:
        p.add_argument("--langsplat-features", metavar="DIR", default=None,
                       help="LangSplat language_features folder (<stem>_s.npy, <stem>_f.npy): import instead of "
                            "segmenting")
        p.add_argument("--labels", metavar="DIR", default=None,
                       help="LangSplat-format labels (default: DATA/label when it exists)")
    p.add_argument("--preset", choices=["cpu", "paper"], default="cpu", help="fit and train presets (default cpu)")
    p.add_argument("--fit-steps", type=positive_int, default=None, help="override the fit preset's step count")
    p.add_argument("--train-steps", type=positive_int, default=None, help="override the train preset's iterations")
    p.add_argument("--dim", type=positive_int, default=None,
                   help="override the train preset's feature-field dims D (cpu 128, paper 512)")
    p.add_argument("--variant", choices=["nested", "flat", "levels"], default=None, help="field variant (default nested)")
    p.add_argument("--depth-source", choices=["render", "gt"], default="render",
                   help="lift segments with the Gaussians' rendered depth (default) or the demo scene's exact depth")
    p.add_argument("--scale-measure", choices=list(SCALE_MEASURES), default=None,
                   help="segment scale: eigenvalue = largest covariance eigenvalue of its 3D points (paper); "
                        "extent = squared diagonal of their robust oriented box (not in the paper; fewer "
                        "segments measured smaller than their own parts). Default: the preset's (cpu "
                        "extent, paper eigenvalue)")
    p.add_argument("--modes", nargs="+", default=["composite", "explicit", "oracle"], help="evaluation modes")
    p.add_argument("--downscale", type=positive_float, default=1.0, help="image downscale factor, as 3DGS -r")
    p.add_argument("--skip-missing", action="store_true",
                   help="drop views whose image file is missing (default: a missing image is an error)")
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def _run_options(args: argparse.Namespace, data: Path, out: Path) -> RunOptions:
    for flag in ("fit_steps", "train_steps", "dim"):
        value = getattr(args, flag)
        if value is not None and value <= 0:
            raise InputError(None, f"--{flag.replace('_', '-')} must be > 0, got {value}")
    return RunOptions(
        data=data, out=out, gaussians=Path(args.gaussians) if args.gaussians else None,
        segmenter=args.segmenter, encoder=args.encoder, model=args.model,
        langsplat_features=Path(args.langsplat_features) if args.langsplat_features else None,
        labels=Path(args.labels) if args.labels else None, preset=args.preset, fit_steps=args.fit_steps,
        train_steps=args.train_steps, dim=args.dim, variant=args.variant, depth_source=args.depth_source,
        scale_measure=args.scale_measure, downscale=args.downscale, skip_missing=args.skip_missing,
        modes=tuple(args.modes), device=args.device,
        quiet=args.quiet)


def _cmd_run(args: argparse.Namespace) -> int:
    start = time.perf_counter()
    result = run_pipeline(_run_options(args, Path(args.data), Path(args.out)))
    print(f"run: {result['run_dir']} in {time.perf_counter() - start:.1f} s"
          + (f"; evaluation: {result['eval']}" if result["eval"] else ""))
    return 0


# ----------------------------------------------------------------------------- run-many
SUMMARY_NAME = "summary"  # DIR/summary.json and DIR/summary.md
SUMMARY_STAGES = ("fit-gaussians", "segments", "train", "eval")


def _eval_mious(eval_json: str | None) -> dict:
    """{mode: {box: mIoU}} of a run's eval.json ({} without evaluation)."""
    if eval_json is None:
        return {}
    scores = json.loads(Path(eval_json).read_text())["scores"]
    return {mode: {box: float(v["miou"]) for box, v in boxes.items()} for mode, boxes in scores.items()}


def run_scene(opt: RunOptions) -> dict:
    """One scene of ``run-many``: :func:`run_pipeline` into ``opt.out``, then the scene's summary
    row. Bad input is the row's status (``failed`` and the error), not an exception, so the
    other scenes go on."""
    from .errors import N2F2Error

    name = Path(opt.out).name
    start = time.perf_counter()
    row = {"scene": name, "data": str(opt.data), "run_dir": str(opt.out)}
    try:
        result = run_pipeline(opt, log=lambda msg: print(f"{name}: {msg}", flush=True))
        mious = _eval_mious(result["eval"])
    except N2F2Error as e:
        return {**row, "status": "failed", "error": str(e), "seconds": round(time.perf_counter() - start, 2),
                "stages": {}, "miou": {}, "eval": None}
    stages = {stage: {"seconds": rec.get("seconds"), "ran": stage in result["ran"]}
              for stage, rec in result["stages"].items()}
    return {**row, "status": "ok", "error": None, "seconds": round(time.perf_counter() - start, 2),
            "stages": stages, "miou": mious, "eval": result["eval"]}


def _summary_markdown(summary: dict) -> str:
    from .eval.reports import markdown_table

    rows = summary["scenes"]
    modes = [m for m in ("composite", "explicit", "oracle") if any(m in r["miou"] for r in rows)]
    modes += sorted({m for r in rows for m in r["miou"]} - set(modes))
    boxes = [b for b in ("exact", "scaled") if any(b in r["miou"].get(m, {}) for r in rows for m in modes)]
    body = []
    for r in rows:
        cells = [r["scene"], r["status"]]
        for m in modes:
            cells.append(" / ".join(f"{100 * r['miou'][m][b]:.1f}" if b in r["miou"].get(m, {}) else "-"
                                    for b in boxes))
        for stage in SUMMARY_STAGES:
            st = r["stages"].get(stage)
            cells.append("-" if st is None or st["seconds"] is None
                         else f"{st['seconds']:.1f}" + ("" if st["ran"] else " (cached)"))
        cells.append(f"{r['seconds']:.1f}")
        body.append(cells)
    box_note = " / ".join(boxes)
    headers = (["scene", "status"] + [f"{m} mIoU % ({box_note})" for m in modes]
               + [f"{s} s" for s in SUMMARY_STAGES] + ["wall s"])
    text = (f"# run-many: {len(rows)} scenes, executor {summary['executor']}, {summary['seconds']:.1f} s\n\n"
            + markdown_table(headers, body))
    failed = [r for r in rows if r["status"] != "ok"]
    if failed:
        text += "\n" + "".join(f"- {r['scene']}: {r['error']}\n" for r in failed)
    text += ("\nmIoU per box of LangSplat's protocol (exact: 30 px box; scaled: box scaled to the image "
             "width). Stage times are those of the stage's last run; (cached): skipped this time, its inputs "
             "unchanged.\n")
    return text


def run_many(opts: list[RunOptions], out: Path, executor, progress: bool = True) -> dict:
    """:func:`run_scene` for every scene, one task each on ``executor`` (serial or Ray), then
    ``out/summary.json`` and ``out/summary.md``. Returns the summary."""
    from tqdm import tqdm

    from .distributed import TaskFailure
    from .io import write_text

    start = time.perf_counter()
    rows: list = [None] * len(opts)
    bar = tqdm(total=len(opts), desc="run-many", unit="scene", disable=not progress)
    with executor:
        for k, row in executor.map(run_scene, opts):
            if isinstance(row, TaskFailure):  # run_scene reports bad input itself; kept for safety
                row = {"scene": Path(opts[k].out).name, "data": str(opts[k].data), "run_dir": str(opts[k].out),
                       "status": "failed", "error": str(row), "seconds": 0.0, "stages": {}, "miou": {}, "eval": None}
            rows[k] = row
            if row["status"] != "ok":
                bar.write(f"run-many: {row['scene']} failed: {row['error']}", file=sys.stderr)
            bar.update(1)
    bar.close()
    summary = {"executor": executor.name, "seconds": round(time.perf_counter() - start, 2), "scenes": rows}
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / f"{SUMMARY_NAME}.json", summary)
    write_text(out / f"{SUMMARY_NAME}.md", _summary_markdown(summary))
    return summary


def _cmd_run_many(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from .distributed import executor_from_args

    out = Path(args.out)
    scenes = [Path(d) for d in args.data]
    names = [d.resolve().name for d in scenes]
    for name in sorted(set(names)):
        same = [str(d) for d, n in zip(scenes, names) if n == name]
        if len(same) > 1:
            raise InputError(None, f"scenes {', '.join(same)} share the folder name {name!r}, and each scene's run "
                             f"goes to {out}/<scene folder name>")
    executor = executor_from_args(args, gpu=str(args.device).startswith("cuda"))
    opts = [_run_options(args, d, out / n) for d, n in zip(scenes, names)]
    if executor.name == "ray":  # stage progress bars do not survive Ray's log streaming
        device = "cuda" if str(args.device).startswith("cuda") else args.device  # the GPU Ray gives the task
        opts = [replace(o, quiet=True, device=device) for o in opts]
    summary = run_many(opts, out, executor, progress=not args.quiet)
    print((out / f"{SUMMARY_NAME}.md").read_text())
    failed = [r["scene"] for r in summary["scenes"] if r["status"] != "ok"]
    if failed:
        raise InputError(None, f"{len(failed)} of {len(scenes)} scenes failed: {', '.join(failed)} "
                         f"(details in {out / SUMMARY_NAME}.md)")
    return 0


DEMO_QUERIES = {  # per demo layout
    "tabletop": ("teapot", "lid of the teapot", "bag of cookies", "cookies", "red mug", "handle of the blue mug"),
    "lounge": ("sofa", "shade of the lamp", "vase of flowers", "flowers", "red book", "wheels of the toy car"),
}


def _cmd_demo(args: argparse.Namespace) -> int:
    from .data.synthetic import GENERATOR_VERSION, generate_demo_scene, write_contact_sheet

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene_dir = out / "scene"
    start = time.perf_counter()
    key = stage_key(views=args.views, width=args.width, height=args.height, seed=args.seed, layout=args.layout,
                    generator=GENERATOR_VERSION)
    cache = StageCache.open(out)
    regenerated = cache.run("demo-scene", key, [scene_dir / "scene.json", scene_dir / "regions.json"],
                            lambda: generate_demo_scene(scene_dir, num_views=args.views, width=args.width,
                                                        height=args.height, seed=args.seed, layout=args.layout,
                                                        show_progress=not args.quiet))
    sheet = out / "contact_sheet.png"
    if regenerated or not sheet.exists():
        write_contact_sheet(scene_dir, sheet)
    print(f"demo scene: {scene_dir}\ncontact sheet: {sheet}")
    if args.scene_only:
        return 0
    result = run_pipeline(_run_options(args, scene_dir, out / "run"))
    # A few relevancy PNGs for a person to look at (raw .npy beside each).
    scene_meta = json.loads((scene_dir / "scene.json").read_text())
    views = [int(v) for v in scene_meta.get("labelled_views", [0])[:2]]
    _cli(["query", out / "run", *DEMO_QUERIES[args.layout], "--views", *views, "--out", out / "queries",
          *(["--quiet"] if args.quiet else []), "--force"])  # the demo's own folder, answered afresh each run
    if result["eval"]:
        md = Path(result["eval"]).with_suffix(".md")
        if md.is_file():
            print(md.read_text())
    print(f"queries: {out / 'queries'}")
    print(f"demo finished in {time.perf_counter() - start:.1f} s")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="generate the built-in demo scene and run the whole pipeline on it",
        description="Generate a built-in synthetic scene (--layout: a tabletop or a lounge; exact ground truth "
                    "at part, object and group level), then fit Gaussians, build the segment bank (ground-truth "
                    "segments; captions embedded by all-MiniLM-L6-v2, an offline stand-in for CLIP), train the nested field, "
                    "evaluate with LangSplat's protocol, and write a few relevancy PNGs.")
    p.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    p.add_argument("--views", type=positive_int, default=40, help="number of views (default: 40)")
    p.add_argument("--width", type=positive_int, default=160, help="image width (default: 160)")
    p.add_argument("--height", type=positive_int, default=120, help="image height (default: 120)")
    p.add_argument("--seed", type=nonneg_int, default=0, help="random seed (default: 0)")
    p.add_argument("--layout", choices=["tabletop", "lounge"], default="tabletop",
                   help="scene layout: tabletop (round table with a tea set and snacks, 6 x 6 m room; every "
                        "preset was tuned on it) or lounge (sofa, floor lamp and a coffee table with small "
                        "objects in a 14 x 11 m room, on a partial arc with close views). Default: tabletop")
    p.add_argument("--scene-only", action="store_true", help="only generate the scene and its contact sheet")
    _add_run_options(p)
    p.set_defaults(func=_cmd_demo)

    r = subparsers.add_parser(
        "run", help="run every stage on a scene: fit, segments, train, eval (each cached)",
        description="Fit Gaussians (or --gaussians), build the segment bank (or --langsplat-features), train "
                    "the nested field, and evaluate when labels exist. Each stage is skipped when its inputs "
                    "are unchanged (RUN/stages.json).")
    r.add_argument("data", metavar="DATA", help="scene folder (COLMAP or nerfstudio), or a folder of photos, "
                                            "posed first by `n2f2 sfm` into DIR/sfm")
    r.add_argument("--out", required=True, metavar="DIR", help="run folder")
    _add_run_options(r)
    r.set_defaults(func=_cmd_run)

    m = subparsers.add_parser(
        "run-many", help="`run` on several scenes, one task per scene (serially or on Ray), and a summary table",
        description="Run every stage (as `n2f2 run`, with the same stage cache) on each scene into "
                    "DIR/<scene folder name>/, one task per scene: serially, or as Ray tasks on this machine "
                    "or a cluster (docs/distributed.md). A scene failing on bad input is reported and the "
                    "others go on; then DIR/summary.md and DIR/summary.json give each scene's mIoU per mode, "
                    "time per stage and status, and the command exits 2 if any scene failed.")
    m.add_argument("data", nargs="+", metavar="SCENE", help="scene folders (COLMAP or nerfstudio) or photo folders")
    m.add_argument("--out", required=True, metavar="DIR", help="folder of the runs (DIR/<scene folder name>/) "
                                                            "and the summary")
    _add_run_options(m, per_scene_inputs=False)
    add_executor_options(m, "scene")
    m.set_defaults(func=_cmd_run_many, gaussians=None, langsplat_features=None, labels=None)
