"""``n2f2 run`` and ``n2f2 demo``: the stages in data-flow order (fit Gaussians -> segment bank ->
nested field -> evaluation), each through its stage's runner under the stage cache of the run
folder (:mod:`.cache`), with the settings of a named preset (:mod:`.presets`)."""

from __future__ import annotations

import shutil
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Optional, TypedDict

from ..errors import InputError
from ..eval.stage import EvalJob, run_eval
from ..gaussians.stage import FitJob, run_fit
from ..io import claim_out_dir
from ..segments.stage import BankJob, run_bank
from ..train.stage import TrainJob, run_train
from .cache import StageCache, file_digest, scene_digest, stage_key, tree_digest
from .preflight import STAGES, check_run_models, needs_posing
from .presets import Preset, default_preset, get_preset

DEFAULT_MODES = ("composite", "explicit", "soft", "oracle")
# Modules with numba kernels beyond the rasterizer's, compiled in the background
# (n2f2.render.numba_backend.compile_in_background): the fit's before its first render goes on,
# the training's while the fit runs, so each stage's first step finds its kernels cached.
BACKGROUND_KERNELS = {
    "first": ("n2f2.gaussians.numba_adam", "n2f2.gaussians.numba_ssim"),
    "later": ("n2f2.train.numba_blend", "n2f2.train.numba_prefix"),
}


class _StageOptions(TypedDict):
    """The keyword settings every stage job of a run shares."""

    downscale: float
    skip_missing: bool
    device: str
    progress: bool


@dataclass
class RunOptions:
    """Settings of ``n2f2 run``; ``None`` means the default that :func:`resolve_defaults`
    picks from the scene and the preset (see there)."""

    data: Path
    out: Path
    gaussians: Path | None = None
    segmenter: str | None = None
    encoder: str | None = None
    model: str | None = None
    sam_model: str | None = None
    langsplat_features: Path | None = None
    labels: Path | None = None
    preset: str | None = None  # None: config.default_preset(device)
    fit_steps: int | None = None
    train_steps: int | None = None
    dim: int | None = None  # feature-field dims D (None: the preset's)
    variant: str | None = None
    depth_source: str = "render"
    scale_measure: str | None = None  # segment scale measure (None: the preset's LiftSettings)
    downscale: float = 1.0
    skip_missing: bool = False  # drop views whose image is missing (every stage drops the same ones)
    modes: tuple[str, ...] = DEFAULT_MODES
    device: str = "cpu"
    quiet: bool = False


def is_demo_scene(data: Path) -> bool:
    """A scene with the built-in demo's ground truth (regions with captions, exact depth)."""
    return (Path(data) / "regions.json").is_file()


def resolve_defaults(opt: RunOptions) -> RunOptions:
    """Fill in the scene-dependent defaults:

    * preset: :func:`n2f2.config.default_preset` of the device;
    * segmenter: ``ground-truth`` on a demo scene, else ``sam`` (the paper's);
    * scale measure: the preset's (:mod:`.presets`);
    * encoder: with ``langsplat_features``, the encoder an n2f2 export recorded beside them
      (``encoder.json``), else ``clip`` (LangSplat's own features are CLIP); otherwise
      ``captions`` (the offline MiniLM stand-in) with the ground-truth segmenter of a demo scene
      (the only segmenter with captions), else ``clip``."""
    demo = is_demo_scene(Path(opt.data))
    segmenter = opt.segmenter or ("ground-truth" if demo else "sam")
    encoder = opt.encoder
    if encoder is None and opt.langsplat_features is not None:
        from ..segments.langsplat import recorded_encoder

        feats = Path(opt.langsplat_features)
        recorded = recorded_encoder(feats) if feats.is_dir() else None
        encoder = recorded["name"] if recorded else "clip"
    if encoder is None:
        encoder = "captions" if demo and segmenter == "ground-truth" else "clip"
    preset = opt.preset or default_preset(opt.device)
    scale_measure = opt.scale_measure or get_preset(preset).lift.scale_measure
    return replace(opt, preset=preset, segmenter=segmenter, encoder=encoder, scale_measure=scale_measure)


def run_pipeline(opt: RunOptions, log: Callable[[str], None] = print) -> dict:
    """Fit Gaussians -> segment bank -> nested field -> evaluation (when labels exist).
    Returns ``{"stages": ..., "run_dir": ..., "ran": [...], "eval": path or None}``.

    Works on any COLMAP or nerfstudio scene: without ground truth the segments are lifted with
    the fitted Gaussians' rendered depth (``depth_source="render"``, the default), and with
    ``langsplat_features`` the bank is imported from LangSplat-format files instead of
    segmenting. Evaluation runs on ``labels`` (default ``DATA/label``) when they exist; query
    types (simple / compound) come from ``DATA/queries.json`` when the scene has one. A stage
    stopped in the middle (its start is recorded in ``stages.json``) is continued by the next
    run with the same inputs: the fit and the training from their checkpoints, the bank from
    its finished images.

    Before the first stage every model the stages that will run load is located (a missing one
    is one line with a command that gets it, :mod:`.preflight`), and the expected time of each
    stage is printed (:mod:`.estimate`), which its ``done in`` line repeats."""
    from ..data.sfm import posed_scene_path

    opt = resolve_defaults(opt)
    check_inputs(opt)
    out = Path(opt.out)
    posing = needs_posing(Path(opt.data))
    if posing:  # structure from motion comes first: the models any stage may load are checked before it
        check_run_models(opt, STAGES)
    claim_out_dir(out, ())  # writable, with room, and ours alone until the command ends
    if posing:  # the rasterizer compiles during structure from motion
        _compile_kernels(opt)
    progress = not opt.quiet
    data = posed_scene_path(Path(opt.data), out / "sfm", progress=progress, log=log)  # photos: pose them first
    labels = labels_dir(opt, data)
    if labels is not None:  # every label file read now: a bad one stops the run in seconds, not after training
        from ..data.labels import read_label_dir

        read_label_dir(labels)
    assert opt.preset is not None  # resolve_defaults chose it
    run = _Run(opt, get_preset(opt.preset), data, out, StageCache.open(out), scene_digest(data), log)
    plan = stage_plan(run, labels)
    check_run_models(opt, plan)  # the models of the stages that will run, before the first of them
    run.cache.expected = _announce(run, labels, plan)  # the calibration before the compile takes a core
    if plan:
        _compile_kernels(opt)  # the first render waits for it
    ply = _gaussians_stage(run)
    bank = _segments_stage(run, ply)
    _train_stage(run, ply, bank)
    eval_json = None if labels is None else _eval_stage(run, labels, bank)
    return {
        "run_dir": str(out),
        "stages": run.cache.records,
        "ran": list(run.cache.ran),
        "eval": None if eval_json is None else str(eval_json),
    }


def check_models_before_work(opt: RunOptions) -> None:
    """Locate the models of the stages a run with ``opt`` will run (of every stage for photos,
    which are posed first), claiming and writing nothing: ``run-many`` does so for every scene
    before the first, so that a missing model stops the command at once. A scene's own bad
    input is left to its run, which reports it as that scene's failure."""
    from ..errors import N2F2Error

    try:
        opt = resolve_defaults(opt)
        data = Path(opt.data)
        stages = list(STAGES) if needs_posing(data) else planned_stages(opt, data)
    except (N2F2Error, OSError):
        return
    check_run_models(opt, stages)


def planned_stages(opt: RunOptions, data: Path) -> list[str]:
    """:func:`stage_plan` of a run with resolved options ``opt`` on the posed scene ``data``,
    from ``opt.out``'s stages.json, writing nothing."""
    assert opt.preset is not None  # resolve_defaults chose it
    out = Path(opt.out)
    run = _Run(opt, get_preset(opt.preset), data, out, StageCache.open(out), scene_digest(data), print)
    return stage_plan(run, labels_dir(opt, data))


def labels_dir(opt: RunOptions, data: Path) -> Optional[Path]:
    """``--labels``, else the scene's ``label`` folder when it has one."""
    return Path(opt.labels) if opt.labels else (data / "label" if (data / "label").is_dir() else None)


def _compile_kernels(opt: RunOptions) -> None:
    """On the CPU, compile the numba kernels in a child process meanwhile (once per process)."""
    if opt.device == "cpu":
        from ..render.numba_backend import compile_in_background

        compile_in_background(**BACKGROUND_KERNELS)


def check_inputs(opt: RunOptions) -> None:
    """Refuse missing folders and impossible options before any work."""
    data = Path(opt.data)
    if not data.is_dir():
        raise InputError(data, "scene folder does not exist")
    if opt.langsplat_features is None:  # segmenter and encoder by name, before any model loads
        from ..segments.bank import check_pairing
        from ..segments.encoders import ENCODERS

        kind = ENCODERS.get(str(opt.encoder))
        check_pairing(str(opt.segmenter), str(opt.encoder), kind is not None and kind.requires_captions)
        if opt.segmenter == "ground-truth" and not is_demo_scene(data):
            raise InputError(
                data,
                "--segmenter ground-truth needs a scene with ground-truth regions (regions/ and "
                "regions.json, as the built-in demo scene has); use --segmenter sam or classical",
            )
    if opt.depth_source == "gt" and not (is_demo_scene(data) and (data / "depth").is_dir()):
        raise InputError(
            data / "depth",
            "--depth-source gt needs the exact depth maps of the demo scene "
            "(depth/*.npy and regions.json); use --depth-source render",
        )
    if opt.gaussians is not None:
        _given_ply(opt)
    if opt.langsplat_features is not None and not Path(opt.langsplat_features).is_dir():
        raise InputError(opt.langsplat_features, "LangSplat features folder does not exist")
    if opt.labels is not None and not Path(opt.labels).is_dir():
        raise InputError(opt.labels, "labels folder does not exist")


@dataclass
class _Run:
    """What every stage of one ``run_pipeline`` call shares."""

    opt: RunOptions
    preset: Preset
    data: Path  # the posed scene
    out: Path
    cache: StageCache
    scene_digest: str
    log: Callable[[str], None]

    def common(self) -> _StageOptions:
        o = self.opt
        return _StageOptions(downscale=o.downscale, skip_missing=o.skip_missing, device=o.device, progress=not o.quiet)


def _fit_key(run: _Run) -> str:
    """The fit's stage key: the scene's content, the preset and the steps, the downscale."""
    opt = run.opt
    fit_key = ["--preset", opt.preset] + (["--steps", opt.fit_steps] if opt.fit_steps else [])
    return stage_key(scene=run.scene_digest, args=fit_key, downscale=opt.downscale)


def _segments_key(run: _Run, ply: Path) -> str:
    """The segments stage's key: scene, Gaussians, depth, models, and the segmenter and encoder
    (or the LangSplat features' content)."""
    opt = run.opt
    common = dict(scene=run.scene_digest, gaussians=file_digest(ply), depth=opt.depth_source, model=opt.model)
    if opt.langsplat_features is not None:
        args = ["--encoder", opt.encoder, "--scale-measure", opt.scale_measure]
        return stage_key(**common, features=tree_digest(Path(opt.langsplat_features)), args=args)
    args = ["--segmenter", opt.segmenter, "--encoder", opt.encoder, "--scale-measure", opt.scale_measure]
    sam = {"sam_model": opt.sam_model} if opt.sam_model else {}  # keys of earlier runs unchanged
    return stage_key(**common, args=args, **sam)


def _train_key(run: _Run, ply: Path, bank: Path) -> str:
    """The training's key: scene, Gaussians, bank, and the settings as the key has always named them."""
    opt = run.opt
    train_key = ["--preset", opt.preset]
    if opt.train_steps:
        train_key += ["--iterations", opt.train_steps]
    if opt.dim:
        train_key += ["--dim", opt.dim]
    if opt.variant:
        train_key += ["--variant", opt.variant]
    return stage_key(
        scene=run.scene_digest, gaussians=file_digest(ply), bank=file_digest(bank / "bank.json"), args=train_key
    )


def _eval_key(run: _Run, labels: Path) -> str:
    """The evaluation's key: the field, the labels, the modes and the query's render."""
    from ..query.engine import DEFAULT_RENDER

    return stage_key(
        field=file_digest(run.out / "field.pt"),
        labels=tree_digest(labels),
        modes=list(run.opt.modes),
        render=DEFAULT_RENDER,  # an evaluation cached with per-Gaussian views is redone
    )


def stage_plan(run: _Run, labels: Optional[Path]) -> list[str]:
    """The stages ``run`` will run, in order; the others are up to date (key and outputs
    recorded in RUN/stages.json) and skipped. A stage after one that runs runs too: its key
    hashes that stage's new outputs."""
    opt, out, cache = run.opt, run.out, run.cache
    ply = _given_ply(opt) if opt.gaussians is not None else out / "gaussians" / "gaussians.ply"
    bank = out / "bank"
    up_to_date = {
        "fit-gaussians": lambda: opt.gaussians is not None or cache.fresh("fit-gaussians", _fit_key(run), [ply]),
        "segments": lambda: cache.fresh("segments", _segments_key(run, ply), [bank / "bank.json"]),
        "train": lambda: cache.fresh("train", _train_key(run, ply, bank), [out / "field.pt"]),
        "eval": lambda: labels is None or cache.fresh("eval", _eval_key(run, labels), [out / "eval" / "eval.json"]),
    }
    plan: list[str] = []
    for stage in STAGES:
        if plan or not up_to_date[stage]():
            plan.append(stage)
    return [s for s in plan if s != "eval" or labels is not None]


def _announce(run: _Run, labels: Optional[Path], plan: list[str]) -> dict[str, float]:
    """Log the scene's size, the machine's measured speed and the expected time of each stage
    of ``plan`` (:mod:`.estimate`) before the first of them; returns ``{stage: seconds}``."""
    if not plan:
        return {}
    from ..data import load_scene
    from .estimate import calibrate, machine_line, scene_size, stage_estimates, total_line

    opt = run.opt
    scene = load_scene(run.data, downscale=opt.downscale, skip_missing=opt.skip_missing)
    size = scene_size(scene, labels)
    speed = calibrate(opt.device)
    estimates = stage_estimates(opt, plan, size, scene, speed)
    run.log(f"[plan] scene: {size.describe(opt.downscale)}")
    run.log(f"[plan] machine: {machine_line(opt.device)}")
    run.log(f"[plan] speed: {speed.describe()}")
    for estimate in estimates:
        run.log(f"[plan] {estimate.line()}")
    if len(estimates) > 1:
        run.log(f"[plan] {total_line(estimates)}")
    return {e.stage: e.seconds for e in estimates}


def _given_ply(opt: RunOptions) -> Path:
    """``--gaussians``: a PLY, or the folder holding gaussians.ply, which must exist."""
    ply = Path(str(opt.gaussians))
    if ply.is_dir():
        ply = ply / "gaussians.ply"
    if not ply.is_file():
        raise InputError(ply, "Gaussians file does not exist")
    return ply


def _gaussians_stage(run: _Run) -> Path:
    """The Gaussians' PLY: given, or fitted into RUN/gaussians."""
    opt = run.opt
    if opt.gaussians is not None:
        return _given_ply(opt)
    fit_dir = run.out / "gaussians"
    ply = fit_dir / "gaussians.ply"
    key = _fit_key(run)
    job = FitJob(
        run.data,
        fit_dir,
        preset=opt.preset,
        overrides={"steps": opt.fit_steps} if opt.fit_steps else {},
        **_continued(run.cache.interrupted("fit-gaussians", key)),
        **run.common(),
    )
    run.cache.run("fit-gaussians", key, [ply], lambda: run_fit(job, log=run.log), run.log)
    return ply


def _segments_stage(run: _Run, ply: Path) -> Path:
    """The segment bank RUN/bank: segmented and embedded, or imported from LangSplat's files."""
    opt = run.opt
    bank = run.out / "bank"
    key = _segments_key(run, ply)
    if opt.langsplat_features is not None:
        source: dict = dict(encoder=opt.encoder, features=Path(opt.langsplat_features))
    else:
        assert opt.segmenter is not None  # resolve_defaults filled it in
        source = dict(segmenter=opt.segmenter, encoder=opt.encoder, sam_model=opt.sam_model)
    job = BankJob(
        run.data,
        bank,
        ply,
        lift=replace(run.preset.lift, scale_measure=opt.scale_measure),
        model=opt.model,
        depth_source=opt.depth_source,
        force=True,
        # A bank this stage left unfinished with the same inputs is finished; any other bank goes.
        keep_unfinished=run.cache.interrupted("segments", key),
        **source,
        **run.common(),
    )

    def build() -> None:
        if bank.exists() and not job.keep_unfinished:  # other inputs: records must not mix
            shutil.rmtree(bank)
        run_bank(job, log=run.log)

    run.cache.run("segments", key, [bank / "bank.json"], build, run.log)
    return bank


def _train_stage(run: _Run, ply: Path, bank: Path) -> None:
    """The nested feature field in RUN (field.pt, train_report.json, ...)."""
    opt = run.opt
    key = _train_key(run, ply, bank)
    resume = run.cache.interrupted("train", key)
    job = TrainJob(
        run.data,
        ply,
        bank,
        run.out,
        preset=opt.preset,
        field_overrides={k: v for k, v in (("dim", opt.dim), ("variant", opt.variant)) if v},
        train_overrides={"iterations": opt.train_steps} if opt.train_steps else {},
        **_continued(resume),
        **run.common(),
    )

    def train() -> None:
        if not resume:  # other inputs: start from scratch
            for stale in ("checkpoint.pt", "field.pt"):
                (run.out / stale).unlink(missing_ok=True)
        run_train(job, log=run.log)

    run.cache.run("train", key, [run.out / "field.pt"], train, run.log)


def _eval_stage(run: _Run, labels: Path, bank: Path) -> Path:
    """The evaluation on ``labels`` in RUN/eval; returns its eval.json."""
    opt = run.opt
    eval_dir = run.out / "eval"
    job = EvalJob(
        run.out,
        labels,
        eval_dir,
        scene=run.data,
        bank=bank,
        modes=opt.modes,
        force=True,
        device=opt.device,
        progress=not opt.quiet,
    )
    key = _eval_key(run, labels)
    run.cache.run("eval", key, [eval_dir / "eval.json"], lambda: run_eval(job, log=run.log), run.log)
    return eval_dir / "eval.json"


def _continued(resume: bool) -> dict:
    """A stage's output folder: continued when the stage was interrupted with the same inputs
    (its checkpoint was kept), else replaced."""
    return {"resume": True} if resume else {"force": True}


# ----------------------------------------------------------------------------- demo
DEMO_QUERIES = {  # per demo layout
    "tabletop": ("teapot", "lid of the teapot", "bag of cookies", "cookies", "red mug", "handle of the blue mug"),
    "lounge": ("sofa", "shade of the lamp", "vase of flowers", "flowers", "red book", "wheels of the toy car"),
}


@dataclass
class DemoScene:
    """The generated scene of ``n2f2 demo`` (see :func:`n2f2.data.synthetic.generate_demo_scene`)."""

    views: int = 40
    width: int = 160
    height: int = 120
    seed: int = 0
    layout: str = "tabletop"


def cached_demo_scene(
    cache: StageCache, scene_dir: Path, spec: DemoScene, progress: bool = True, log: Callable[[str], None] = print
) -> bool:
    """Generate the demo scene ``spec`` into ``scene_dir`` unless ``cache`` holds it (keyed on
    its settings and the generator's version). Returns True when it was generated."""
    from ..data.scene import SCENE_META_NAME
    from ..data.synthetic import GENERATOR_VERSION, generate_demo_scene

    key = stage_key(
        views=spec.views,
        width=spec.width,
        height=spec.height,
        seed=spec.seed,
        layout=spec.layout,
        generator=GENERATOR_VERSION,
    )
    return cache.run(
        "demo-scene",
        key,
        [scene_dir / SCENE_META_NAME, scene_dir / "regions.json"],
        lambda: generate_demo_scene(
            scene_dir,
            num_views=spec.views,
            width=spec.width,
            height=spec.height,
            seed=spec.seed,
            layout=spec.layout,
            show_progress=progress,
        ),
        log,
    )


def demo_scene(out: Path, spec: DemoScene, progress: bool = True, log: Callable[[str], None] = print) -> Path:
    """Generate the demo scene into ``out/scene`` (cached in ``out/stages.json``) and its contact
    sheet ``out/contact_sheet.png``."""
    from ..data.synthetic import write_contact_sheet

    out = Path(out)
    claim_out_dir(out, ())
    scene_dir = out / "scene"
    regenerated = cached_demo_scene(StageCache.open(out), scene_dir, spec, progress, log)
    sheet = out / "contact_sheet.png"
    if regenerated or not sheet.exists():
        write_contact_sheet(scene_dir, sheet)
    return scene_dir


def demo_queries(
    out: Path,
    scene_dir: Path,
    run_dir: Path,
    layout: str,
    device: str = "cpu",
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> Path:
    """A few relevancy PNGs for a person to look at (raw .npy beside each) in ``out/queries``,
    answered afresh each run: the layout's demo queries in its first two labelled views."""
    from ..data.scene import read_scene_meta
    from ..query.stage import QueryJob, run_query

    views = [int(v) for v in read_scene_meta(scene_dir).get("labelled_views", [0])[:2]]
    job = QueryJob(
        run_dir, DEMO_QUERIES[layout], out / "queries", views=views, force=True, device=device, progress=progress
    )
    run_query(job, log=log)
    return out / "queries"
