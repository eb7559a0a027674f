"""The training stage's runner: ``n2f2 train`` and ``n2f2 run`` / ``demo`` / ``run-many`` train a
feature field through :func:`run_train`, which claims the run folder, builds the configs from a
preset and overrides, reads the scene, the segment bank and the Gaussians before anything is
replaced, trains, and prints the summary line. The bench trains its variants through it too,
giving each variant's configs whole and a step callback that meters activations."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Optional

from ..config import StageJob, default_preset, option_flag
from ..errors import InputError
from ..field.model import FieldConfig
from .config import TrainConfig

Log = Callable[[str], None]


@dataclass
class TrainJob(StageJob):
    """One training run: what ``n2f2 train`` takes on its command line."""

    data: Path  # scene folder
    gaussians: Path  # gaussians.ply, or the folder holding it
    bank: Path  # segment bank folder
    out: Path  # run folder
    preset: Optional[str] = None  # None: config.default_preset(device)
    field_overrides: dict[str, Any] = field(default_factory=dict)  # FieldConfig fields set explicitly
    train_overrides: dict[str, Any] = field(default_factory=dict)  # TrainConfig fields set explicitly
    train_on_all: bool = False  # also train on the scene's test views
    seed: int = 0
    # Configs given whole (the bench's variants): they replace the preset (and a resumed
    # checkpoint's); the overrides still apply on top.
    field_config: Optional[FieldConfig] = None
    train_config: Optional[TrainConfig] = None
    callback: Optional[Callable[[int, float], None]] = None  # after each step: (step, loss)


def gaussians_path(path: str | Path) -> Path:
    """The PLY of ``path`` (a file, or a fit folder holding ``gaussians.ply``), which must exist."""
    p = Path(path)
    if p.is_dir():
        p = p / "gaussians.ply"
    if not p.is_file():
        raise InputError(p, "Gaussians file does not exist (run `n2f2 fit-gaussians` first)")
    return p


def job_configs(job: TrainJob, out: Path) -> tuple[FieldConfig, TrainConfig]:
    """The field and training configs of ``job``: the preset's (or, resuming, the checkpoint's)
    with the overrides applied."""
    from .checkpoint import saved_configs

    for cls, over in ((FieldConfig, job.field_overrides), (TrainConfig, job.train_overrides)):
        for name, value in over.items():
            if isinstance(value, (int, float)) and not isinstance(value, bool) and value < 0:
                raise InputError(None, f"{option_flag(cls, name)} must be >= 0, got {value}")
    saved = saved_configs(out) if job.resume else None
    preset = job.preset or default_preset(job.device)
    try:
        if job.field_config is not None and job.train_config is not None:
            field_config = replace(job.field_config, **job.field_overrides)
            config = job.train_config
        elif saved is not None:  # a resumed run keeps the checkpoint's settings; overrides may change them
            field_config = replace(saved[0], **job.field_overrides)
            config = saved[1]
        else:
            field_config = replace(FieldConfig.preset(preset), **job.field_overrides)
            config = replace(TrainConfig.preset(preset), seed=job.seed)
        config = replace(config, device=job.device, **job.train_overrides)
        if job.train_on_all:
            config = replace(config, holdout=False)
    except ValueError as e:
        raise InputError(None, str(e)) from None
    return field_config, config


def run_train(job: TrainJob, log: Log = print) -> dict:
    """Train the field of ``job`` into ``job.out`` (``field.pt``, ``train_report.json``,
    ``checkpoint.pt``, the lift, a copy of the Gaussians) and return the training report."""
    from ..data import load_scene
    from ..gaussians import read_ply
    from ..io import claim_out_dir, remove_results
    from ..segments import SegmentBank
    from .config import RESULT_NAMES
    from .trainer import train_field

    if not job.downscale > 0:
        raise InputError(None, f"--downscale must be > 0, got {job.downscale}")
    out = Path(job.out)
    present = claim_out_dir(out, RESULT_NAMES, resume=job.resume, force=job.force)
    field_config, config = job_configs(job, out)
    gpath = gaussians_path(job.gaussians)
    scene = load_scene(job.data, downscale=job.downscale, skip_missing=job.skip_missing)
    bank = SegmentBank.open(job.bank)
    gaussians = read_ply(gpath)
    if job.force:  # the inputs are read and match: now the old results go
        bank.validate_against(scene)
        remove_results(out, present)
    report = train_field(
        scene,
        gaussians,
        bank,
        out,
        field_config=field_config,
        config=config,
        resume=job.resume,
        progress=job.progress,
        callback=job.callback,
        skip_missing=job.skip_missing,
        paths={
            "scene": str(Path(job.data).resolve()),
            "gaussians": str(gpath.resolve()),
            "bank": str(Path(job.bank).resolve()),
        },
    )
    log(
        f"train: {report['steps']} steps ({field_config.variant}, D={field_config.dim}, "
        f"{'deferred' if config.deferred else 'non-deferred'}), final loss {report['final_loss']:.5f}, "
        f"{report['time_per_iteration_s'] * 1000:.0f} ms/step, peak RSS {report['peak_rss_mb']:.0f} MB -> {out}"
        if report["time_per_iteration_s"]
        else f"train: already at step {report['steps']} -> {out}"
    )
    return report
