"""The fit stage's runner: ``n2f2 fit-gaussians``, ``n2f2 run`` and the bench all fit a scene's
Gaussians through :func:`run_fit`, which claims the output folder, poses photos, loads the
scene, builds the config from a preset and overrides, fits, and prints the summary line."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Optional

from ..config import StageJob, default_preset, option_flag
from ..errors import InputError
from .fit_config import FitConfig

Log = Callable[[str], None]


@dataclass
class FitJob(StageJob):
    """One fit: what ``n2f2 fit-gaussians`` takes on its command line."""

    data: Path  # scene folder, or a folder of photos (posed first by sfm into OUT/sfm)
    out: Path
    preset: Optional[str] = None  # None: config.default_preset(device)
    overrides: dict[str, Any] = field(default_factory=dict)  # FitConfig fields set explicitly
    init: Optional[str] = None  # "points", "random" or an INRIA PLY; None: points when the scene has them
    seed: int = 0


def fit_results() -> tuple[str, ...]:
    """The files and folders a fit writes into its folder."""
    from .fit import BACKGROUND_NAME, CHECKPOINT_NAME, PLY_NAME, REPORT_NAME, TEST_RENDERS_DIR

    return (PLY_NAME, CHECKPOINT_NAME, REPORT_NAME, BACKGROUND_NAME, TEST_RENDERS_DIR)


def summary_line(report, out: Path) -> str:  # report: FitReport
    test = "n/a" if report.test_psnr is None else f"{report.test_psnr:.2f} dB"
    depth = (
        ""
        if report.depth_median_rel_extent is None
        else f", median depth error {100 * report.depth_median_rel_extent:.2f}% of extent"
    )
    return (
        f"fit-gaussians: {report.steps} steps, {report.num_gaussians} Gaussians, "
        f"train PSNR {report.train_psnr:.2f} dB, test PSNR {test}{depth}, {report.wall_time_s:.0f} s -> {out}"
    )


def run_fit(job: FitJob, log: Log = print):  # -> FitReport
    """Fit ``job.data``'s Gaussians into ``job.out`` (``gaussians.ply``, ``fit_report.json``,
    ``checkpoint.pt``, ...). The folder is claimed first (refused when it holds results and
    neither ``resume`` nor ``force`` is set); with ``force`` the old results go only once the
    scene and the initialisation are read. A resumed fit keeps its checkpoint's schedule, which
    only ``overrides`` change."""
    from ..data import load_scene
    from ..data.sfm import posed_scene_path
    from ..io import claim_out_dir, remove_results
    from .fit import CHECKPOINT_NAME, fit_gaussians, saved_config
    from .ply import read_ply

    for name, value in job.overrides.items():
        if not value >= 0:  # NaN too
            raise InputError(None, f"{option_flag(FitConfig, name)} must be >= 0, got {value}")
    if not job.downscale > 0:
        raise InputError(None, f"--downscale must be > 0, got {job.downscale}")
    out = Path(job.out)
    present = claim_out_dir(out, fit_results(), resume=job.resume, force=job.force)
    if job.resume and present and CHECKPOINT_NAME not in present:  # a fresh start would replace them
        raise InputError(
            out,
            f"--resume: no {CHECKPOINT_NAME} to continue from, but the folder holds "
            f"results ({', '.join(present)}); pass --force to replace them, or choose another --out",
        )
    base = saved_config(out) if job.resume else None
    data = posed_scene_path(Path(job.data), out / "sfm", progress=job.progress, log=log)  # photos: pose them
    scene = load_scene(data, downscale=job.downscale, skip_missing=job.skip_missing)
    init: Any = job.init
    if init is not None and init not in ("points", "random"):
        if Path(init).suffix.lower() != ".ply":
            raise InputError(None, f"--init must be points, random or a .ply file, got {init!r}")
        init = read_ply(init)
    if base is None:
        preset = job.preset or default_preset(job.device)
        base = FitConfig.for_scene(preset, scene, steps=job.overrides.get("steps"), init=init, seed=job.seed)
    config = replace(base, device=job.device, **job.overrides)
    if job.force:  # the inputs are read: now the old results go
        remove_results(out, present)
    report = fit_gaussians(scene, config, out, resume=job.resume, init=init, progress=job.progress)
    log(summary_line(report, out))
    return report
