"""``n2f2 run`` and ``n2f2 demo``: the stages in data-flow order (fit Gaussians -> segment bank ->
nested field -> evaluation), each run through :mod:`.stages` under the stage cache of the run
folder (:mod:`.cache`), with the settings of a named preset (:mod:`.presets`)."""

from __future__ import annotations

import shutil
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, TypedDict

from ..errors import InputError
from ..io import claim_out_dir
from . import stages
from .cache import StageCache, file_digest, scene_digest, stage_key, tree_digest
from .presets import DEFAULT_PRESET, get_preset

DEFAULT_MODES = ("composite", "explicit", "soft", "oracle")
# Modules with numba kernels beyond the rasterizer's, compiled in the background
# (n2f2.render.numba_backend.compile_in_background): the fit's before its first render goes on,
# the training's while the fit runs, so each stage's first step finds its kernels cached.
BACKGROUND_KERNELS = {
    "first": ("n2f2.gaussians.numba_adam", "n2f2.gaussians.numba_ssim"),
    "later": ("n2f2.train.numba_blend", "n2f2.train.numba_prefix"),
}


class _StageOptions(TypedDict):
    """The keyword settings every stage of a run shares."""

    downscale: float
    skip_missing: bool
    device: str
    progress: bool
    log: Callable[[str], None]


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
    preset: str = DEFAULT_PRESET
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

    * segmenter: ``ground-truth`` on a demo scene, else ``sam`` (the paper's);
    * scale measure: the preset's (:mod:`.presets`);
    * encoder: with ``langsplat_features``, the encoder an n2f2 export recorded beside them
      (``encoder.json``), else ``clip`` (LangSplat's own features are CLIP); otherwise
      ``captions`` (the offline MiniLM stand-in) on a demo scene, else ``clip``."""
    demo = is_demo_scene(Path(opt.data))
    segmenter = opt.segmenter or ("ground-truth" if demo else "sam")
    encoder = opt.encoder
    if encoder is None and opt.langsplat_features is not None:
        from ..segments.langsplat import recorded_encoder

        feats = Path(opt.langsplat_features)
        recorded = recorded_encoder(feats) if feats.is_dir() else None
        encoder = recorded["name"] if recorded else "clip"
    if encoder is None:
        encoder = "captions" if demo else "clip"
    scale_measure = opt.scale_measure or get_preset(opt.preset).lift.scale_measure
    return replace(opt, segmenter=segmenter, encoder=encoder, scale_measure=scale_measure)


def run_pipeline(opt: RunOptions, log: Callable[[str], None] = print) -> dict:
    """Fit Gaussians -> segment bank -> nested field -> evaluation (when labels exist).
    Returns ``{"stages": ..., "run_dir": ..., "ran": [...], "eval": path or None}``.

    Works on any COLMAP or nerfstudio scene: without ground truth the segments are lifted with
    the fitted Gaussians' rendered depth (``depth_source="render"``, the default), and with
    ``langsplat_features`` the bank is imported from LangSplat-format files instead of
    segmenting. Evaluation runs on ``labels`` (default ``DATA/label``) when they exist; query
    types (simple / compound) come from ``DATA/queries.json`` when the scene has one."""
    opt = resolve_defaults(opt)
    preset = get_preset(opt.preset)
    data, out = Path(opt.data), Path(opt.out)
    if not data.is_dir():
        raise InputError(data, "scene folder does not exist")
    if opt.depth_source == "gt" and not (is_demo_scene(data) and (data / "depth").is_dir()):
        raise InputError(
            data / "depth",
            "--depth-source gt needs the exact depth maps of the demo scene "
            "(depth/*.npy and regions.json); use --depth-source render",
        )
    if opt.langsplat_features is not None and not Path(opt.langsplat_features).is_dir():
        raise InputError(opt.langsplat_features, "LangSplat features folder does not exist")
    if opt.labels is not None and not Path(opt.labels).is_dir():
        raise InputError(opt.labels, "labels folder does not exist")
    claim_out_dir(out, ())  # writable, with room, and ours alone until the command ends
    if opt.device == "cpu":  # compile the rasterizer while the scene is read; the first render waits
        from ..render.numba_backend import compile_in_background

        compile_in_background(**BACKGROUND_KERNELS)
    cache = StageCache.open(out)
    progress = not opt.quiet
    common = _StageOptions(
        downscale=opt.downscale, skip_missing=opt.skip_missing, device=opt.device, progress=progress, log=log
    )
    from ..data.sfm import posed_scene_path

    data = posed_scene_path(data, out / "sfm", progress=progress, log=log)  # photos: pose them first
    sdig = scene_digest(data)
    labels = Path(opt.labels) if opt.labels else (data / "label" if (data / "label").is_dir() else None)
    if labels is not None:  # every label file read now: a bad one stops the run in seconds, not after training
        from ..data.labels import read_label_dir

        read_label_dir(labels)

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
        fit_key = ["--preset", opt.preset] + (["--steps", opt.fit_steps] if opt.fit_steps else [])
        cache.run(
            "fit-gaussians",
            stage_key(scene=sdig, args=fit_key, downscale=opt.downscale),
            [ply],
            lambda: stages.fit_gaussians(data, fit_dir, preset, opt.fit_steps, **common),
            log,
        )
    gdig = file_digest(ply)

    # 2. Segment bank.
    bank = out / "bank"
    lift = replace(preset.lift, scale_measure=opt.scale_measure)
    if opt.langsplat_features is not None:
        feats = Path(opt.langsplat_features)
        seg_key = stage_key(
            scene=sdig,
            gaussians=gdig,
            features=tree_digest(feats),
            args=["--encoder", opt.encoder, "--scale-measure", opt.scale_measure],
            depth=opt.depth_source,
            model=opt.model,
        )

        def build() -> None:
            stages.import_langsplat_bank(
                data,
                bank,
                ply,
                feats,
                encoder=opt.encoder,
                lift=lift,
                model=opt.model,
                depth_source=opt.depth_source,
                **common,
            )
    else:
        seg_key = stage_key(
            scene=sdig,
            gaussians=gdig,
            args=["--segmenter", opt.segmenter, "--encoder", opt.encoder, "--scale-measure", opt.scale_measure],
            depth=opt.depth_source,
            model=opt.model,
            **({"sam_model": opt.sam_model} if opt.sam_model else {}),  # keys of earlier runs unchanged
        )

        def build() -> None:
            # resolve_defaults filled in both.
            assert opt.segmenter is not None and opt.encoder is not None
            stages.build_segment_bank(
                data,
                bank,
                ply,
                segmenter=opt.segmenter,
                encoder=opt.encoder,
                lift=lift,
                model=opt.model,
                sam_model=opt.sam_model,
                depth_source=opt.depth_source,
                **common,
            )

    def build_bank() -> None:
        if bank.exists():  # inputs changed: a resumed extraction would mix old and new records
            shutil.rmtree(bank)
        build()

    cache.run("segments", seg_key, [bank / "bank.json"], build_bank, log)

    # 3. Nested feature field.
    field_over = {k: v for k, v in (("dim", opt.dim), ("variant", opt.variant)) if v}
    field_config = replace(preset.field, **field_over)
    train_config = replace(
        preset.train, seed=0, device=opt.device, **({"iterations": opt.train_steps} if opt.train_steps else {})
    )
    train_key = ["--preset", opt.preset]  # the settings as the key has always named them
    if opt.train_steps:
        train_key += ["--iterations", opt.train_steps]
    if opt.dim:
        train_key += ["--dim", opt.dim]
    if opt.variant:
        train_key += ["--variant", opt.variant]

    def train() -> None:
        for stale in ("checkpoint.pt", "field.pt"):  # inputs changed: start from scratch
            (out / stale).unlink(missing_ok=True)
        stages.train_field(
            data,
            ply,
            bank,
            out,
            field_config=field_config,
            train_config=train_config,
            downscale=opt.downscale,
            skip_missing=opt.skip_missing,
            progress=progress,
            log=log,
        )

    cache.run(
        "train",
        stage_key(scene=sdig, gaussians=gdig, bank=file_digest(bank / "bank.json"), args=train_key),
        [out / "field.pt"],
        train,
        log,
    )

    # 4. Evaluation, when labels exist.
    eval_json = None
    if labels is not None:
        from ..query.engine import DEFAULT_RENDER

        eval_dir = out / "eval"
        eval_json = eval_dir / "eval.json"
        cache.run(
            "eval",
            stage_key(
                field=file_digest(out / "field.pt"),
                labels=tree_digest(labels),
                modes=list(opt.modes),
                render=DEFAULT_RENDER,  # an evaluation cached with per-Gaussian views is redone
            ),
            [eval_json],
            lambda: stages.evaluate(
                out,
                labels,
                eval_dir,
                scene=data,
                bank=bank,
                modes=opt.modes,
                device=opt.device,
                progress=progress,
                log=log,
            ),
            log,
        )
    return {
        "run_dir": str(out),
        "stages": cache.records,
        "ran": list(cache.ran),
        "eval": None if eval_json is None else str(eval_json),
    }


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
    from ..data.synthetic import GENERATOR_VERSION

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
        lambda: stages.generate_demo_scene(
            scene_dir,
            views=spec.views,
            width=spec.width,
            height=spec.height,
            seed=spec.seed,
            layout=spec.layout,
            progress=progress,
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

    views = [int(v) for v in read_scene_meta(scene_dir).get("labelled_views", [0])[:2]]
    stages.answer_queries(
        run_dir, DEMO_QUERIES[layout], views, out / "queries", device=device, progress=progress, log=log
    )
    return out / "queries"
