"""The stages of the pipeline as typed functions over the library: each does what its command
does with ``--force`` (``fit-gaussians``, ``segments``, ``segments-from-langsplat``, ``train``,
``eval``, ``query``, ``demo --scene-only``), writing the same files into its output folder, and
returns its report. A previous result in the folder is replaced once the new inputs are read.
:func:`~n2f2.pipeline.run.run_pipeline` and the ablation bench call them under the stage cache.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Callable, Optional, Sequence

from ..errors import InputError

if TYPE_CHECKING:
    from ..eval.runner import EvalResult
    from ..field.model import FieldConfig
    from ..gaussians.fit import FitReport
    from ..segments.lifting import LiftSettings
    from ..train.trainer import TrainConfig
    from .presets import Preset

Log = Callable[[str], None]


def _claim(out: Path, results: Sequence[str]) -> list[str]:
    """The previous results in ``out`` (removed by the caller once the inputs are read)."""
    from ..io import claim_out_dir

    return claim_out_dir(out, results, force=True)


def fit_gaussians(
    data: Path,
    out: Path,
    preset: "Preset",
    steps: Optional[int] = None,
    *,
    seed: int = 0,
    downscale: float = 1.0,
    skip_missing: bool = False,
    device: str = "cpu",
    progress: bool = True,
    log: Log = print,
) -> "FitReport":
    """Fit the scene's Gaussians with ``preset``'s schedule into ``out`` (``gaussians.ply``,
    ``fit_report.json``, ``checkpoint.pt``), as ``n2f2 fit-gaussians``."""
    from ..data import load_scene
    from ..gaussians import fit
    from ..io import remove_results

    present = _claim(
        out, (fit.PLY_NAME, fit.CHECKPOINT_NAME, fit.REPORT_NAME, fit.BACKGROUND_NAME, fit.TEST_RENDERS_DIR)
    )
    scene = load_scene(data, downscale=downscale, skip_missing=skip_missing)
    config = preset.fit_config(scene, steps=steps, seed=seed, device=device)
    remove_results(out, present)
    report = fit.fit_gaussians(scene, config, out, progress=progress)
    test = "n/a" if report.test_psnr is None else f"{report.test_psnr:.2f} dB"
    depth = (
        ""
        if report.depth_median_rel_extent is None
        else f", median depth error {100 * report.depth_median_rel_extent:.2f}% of extent"
    )
    log(
        f"fit-gaussians: {report.steps} steps, {report.num_gaussians} Gaussians, "
        f"train PSNR {report.train_psnr:.2f} dB, test PSNR {test}{depth}, {report.wall_time_s:.0f} s -> {out}"
    )
    return report


def _bank_results(out: Path) -> list[str]:
    from ..segments.bank import RECORD_FILES

    records = (
        [d.name for d in out.iterdir() if d.is_dir() and any((d / f).is_file() for f in RECORD_FILES)]
        if out.is_dir()
        else []
    )
    return ["bank.json", *sorted(records)]


def build_segment_bank(
    data: Path,
    out: Path,
    gaussians: Optional[Path],
    *,
    segmenter: str,
    encoder: str,
    lift: "LiftSettings",
    model: Optional[str] = None,
    sam_model: Optional[str] = None,
    depth_source: str = "render",
    downscale: float = 1.0,
    skip_missing: bool = False,
    device: str = "cpu",
    progress: bool = True,
    log: Log = print,
) -> dict:
    """Segment, embed and lift every image into the segment bank ``out``, as ``n2f2 segments``.
    A bank this stage left unfinished (interrupted: ``bank.json`` says ``complete: false``)
    with the same settings is finished, not started again."""
    from ..io import remove_results
    from ..segments.bank import bank_header, build_bank, unfinished_bank
    from ..segments.setup import SegmentsSetup, report_lines

    present = _claim(out, _bank_results(out))
    setup = SegmentsSetup(
        data=str(data),
        downscale=float(downscale),
        skip_missing=skip_missing,
        depth_source=depth_source,
        gaussians=None if gaussians is None else str(gaussians),
        segmenter=segmenter,
        encoder=encoder,
        model=model,
        sam_model=sam_model,
        device=str(device),
    )
    scene, source, depth = setup.build()
    if not unfinished_bank(out, bank_header(scene, source, depth_source, lift)):
        remove_results(out, present)
    report = build_bank(scene, source, depth, out, depth_source=depth_source, lift=lift, progress=progress)
    for line in report_lines(report):
        log(line)
    return report


def import_langsplat_bank(
    data: Path,
    out: Path,
    gaussians: Optional[Path],
    features: Path,
    *,
    encoder: Optional[str],
    lift: "LiftSettings",
    model: Optional[str] = None,
    depth_source: str = "render",
    downscale: float = 1.0,
    skip_missing: bool = False,
    device: str = "cpu",
    progress: bool = True,
    log: Log = print,
) -> dict:
    """The segment bank ``out`` from LangSplat's ``language_features``, as
    ``n2f2 segments-from-langsplat``."""
    from ..io import remove_results
    from ..segments.bank import build_bank
    from ..segments.setup import depth_provider, langsplat_source, load_bank_scene, report_lines

    present = _claim(out, _bank_results(out))
    source = langsplat_source(features, encoder, model)
    scene = load_bank_scene(data, downscale, skip_missing)
    depth = depth_provider(scene, depth_source, gaussians, device)
    source.prepare(scene.image_names, [(c.height, c.width) for c in scene.cameras])  # every file checked
    remove_results(out, present)
    report = build_bank(scene, source, depth, out, depth_source=depth_source, lift=lift, progress=progress)
    for line in report_lines(report):
        log(line)
    return report


def train_field(
    data: Path,
    gaussians: Path,
    bank: Path,
    out: Path,
    *,
    field_config: "FieldConfig",
    train_config: "TrainConfig",
    downscale: float = 1.0,
    skip_missing: bool = False,
    progress: bool = True,
    log: Log = print,
) -> dict:
    """Train the feature field into the run folder ``out`` (``field.pt``, ``train_report.json``,
    ``checkpoint.pt``, a copy of the Gaussians), from scratch, as ``n2f2 train``."""
    from ..data import load_scene
    from ..gaussians import read_ply
    from ..io import remove_results
    from ..segments import SegmentBank
    from ..train import trainer

    present = _claim(out, trainer.RESULT_NAMES)
    scene = load_scene(data, downscale=downscale, skip_missing=skip_missing)
    segment_bank = SegmentBank.open(bank)
    g = read_ply(gaussians)
    segment_bank.validate_against(scene)
    remove_results(out, present)
    report = trainer.train_field(
        scene,
        g,
        segment_bank,
        out,
        field_config=field_config,
        config=train_config,
        progress=progress,
        paths={
            "scene": str(Path(data).resolve()),
            "gaussians": str(Path(gaussians).resolve()),
            "bank": str(Path(bank).resolve()),
        },
    )
    if report["time_per_iteration_s"]:
        log(
            f"train: {report['steps']} steps ({field_config.variant}, D={field_config.dim}, "
            f"{'deferred' if train_config.deferred else 'non-deferred'}), final loss {report['final_loss']:.5f}, "
            f"{report['time_per_iteration_s'] * 1000:.0f} ms/step, peak RSS {report['peak_rss_mb']:.0f} MB -> {out}"
        )
    return report


def evaluate(
    run_dir: Path,
    labels: Path,
    out: Path,
    *,
    scene: Optional[Path] = None,
    bank: Optional[Path] = None,
    modes: Optional[Sequence[str]] = None,
    temperature: Optional[float] = None,  # QueryConfig.temperature; None: its default
    device: str = "cpu",
    relevancy: bool = True,
    progress: bool = True,
    encoder: object = None,
    log: Log = print,
) -> "EvalResult":
    """Score a run on LangSplat-format labels into ``out`` (``eval.json``, ``eval.md``, plots,
    relevancy maps unless ``relevancy`` is False), as ``n2f2 eval``."""
    from ..eval.reports import eval_results, mode_summary_lines, write_eval_outputs
    from ..eval.runner import EvalConfig, evaluate_run
    from ..io import remove_results
    from ..query.engine import QueryConfig

    if temperature is not None and not temperature > 0:
        raise InputError(None, f"temperature must be > 0, got {temperature}")
    present = _claim(out, eval_results(out))
    config = EvalConfig(
        modes=tuple(modes) if modes else None, missing_frames="error", rescale_labels=False, progress=progress
    )
    result = evaluate_run(
        run_dir,
        labels,
        scene=scene,
        bank=bank,
        config=config,
        query_config=QueryConfig() if temperature is None else QueryConfig(temperature=temperature),
        device=device,
        encoder=encoder,
        relevancy_dir=out / "relevancy" if relevancy else None,
        on_ready=lambda: remove_results(out, present),
    )
    write_eval_outputs(result, out)
    for line in mode_summary_lines(result):
        log(line)
    for note in result.notes:
        log(f"note: {note}")
    log(f"eval: {result.scores[result.modes[0]]['exact'].num_pairs} pairs in {result.seconds:.1f} s -> {out}")
    return result


def generate_demo_scene(
    out: Path, *, views: int, width: int, height: int, seed: int, layout: str, progress: bool = True
) -> Path:
    """The built-in demo scene in ``out`` (see :func:`n2f2.data.synthetic.generate_demo_scene`)."""
    from ..data import synthetic

    return synthetic.generate_demo_scene(
        out, num_views=views, width=width, height=height, seed=seed, layout=layout, show_progress=progress
    )


def answer_queries(
    run_dir: Path,
    texts: Sequence[str],
    views: Sequence[int],
    out: Path,
    *,
    device: str = "cpu",
    progress: bool = True,
    log: Log = print,
) -> dict:
    """Relevancy maps, masks and heatmaps of ``texts`` in ``views`` with the evaluation
    protocol's settings (composite mode, 30 px box, threshold 0.4), replacing an earlier answer
    in ``out``, as ``n2f2 query``."""
    from ..query.answer import answer_queries as answer
    from ..query.maps import LANGSPLAT_BOX_SIZE, LANGSPLAT_THRESHOLD

    summary = answer(
        run_dir,
        texts,
        views,
        out,
        mask_threshold=LANGSPLAT_THRESHOLD,
        box_size=LANGSPLAT_BOX_SIZE,
        force=True,
        device=device,
        progress=progress,
    )
    log(f"query: {len(texts)} queries x {len(summary['views'])} views (composite) -> {out}")
    return summary
