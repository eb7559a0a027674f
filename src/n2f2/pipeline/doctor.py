"""``n2f2 doctor DATA [run's options]``: what ``n2f2 run`` would check and expect, one line each,
without running or writing anything: the scene and its size, the models the stages load (found
or not, and where), the machine (CPU, threads, CUDA), the output folder when ``--out`` is given
(whose up-to-date stages are left out, as ``run`` skips them), and the expected time of each
stage from the scene's size and the machine's measured speed (:mod:`.estimate`). Exit status 0
when everything needed is present, 2 otherwise."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

from ..errors import N2F2Error
from .preflight import STAGES, model_line, needs_posing, output_folder_problem, run_models
from .run import RunOptions, check_inputs, labels_dir, planned_stages, resolve_defaults

OK, PROBLEM = "ok     ", "PROBLEM"  # the first column of every line


@dataclass
class _Report:
    """The lines printed so far and the problems among them."""

    log: Callable[[str], None]
    problems: int = 0
    scene: object = None  # the loaded scene, when it could be read
    labels: Optional[Path] = None

    def ok(self, text: str) -> None:
        self.log(f"{OK} {text}")

    def problem(self, text: str) -> None:
        self.problems += 1
        self.log(f"{PROBLEM} {text}")


def run_doctor(opt: RunOptions, out_given: bool, log: Callable[[str], None] = print) -> int:
    """Print the checks of a run with options ``opt`` (``opt.out`` only when ``out_given``);
    return the exit status: 0 when nothing needed is missing, else 2."""
    report = _Report(log)
    try:
        opt = resolve_defaults(opt)
    except N2F2Error as e:
        report.problem(str(e))
        return 2
    log(
        f"n2f2 doctor: {opt.data} with --segmenter {opt.segmenter} --encoder {opt.encoder} "
        f"--preset {opt.preset} --device {opt.device} --downscale {opt.downscale:g}"
    )
    try:
        check_inputs(opt)
    except N2F2Error as e:
        report.problem(str(e))
    stages = _scene_and_stages(opt, out_given, report)
    _models(opt, stages, report)
    _machine(opt, report)
    if out_given:
        problem, described = output_folder_problem(Path(opt.out))
        if problem:
            report.problem(f"output folder: {problem}")
        else:
            report.ok(f"output folder: {described}")
    if report.scene is not None and stages:
        _estimates(opt, stages, report)
    if report.problems:
        log(f"doctor: {report.problems} problem(s); `n2f2 run` would stop on the first")
        return 2
    log("doctor: everything needed is present")
    return 0


def _scene_and_stages(opt: RunOptions, out_given: bool, report: _Report) -> list[str]:
    """The scene's line (loaded into ``report.scene``) and the stages a run would run: those not
    up to date in ``--out``, or every stage the options call for."""
    from ..data import load_scene
    from .estimate import scene_size

    data = Path(opt.data)
    stages = [s for s in STAGES if not (s == "fit-gaussians" and opt.gaussians is not None)]
    if not data.is_dir():
        return stages  # check_inputs reported it
    if needs_posing(data):
        from ..data.sfm import find_photo_folder, list_photos

        folder = find_photo_folder(data)
        assert folder is not None  # needs_posing found it
        report.ok(
            f"scene: {len(list_photos(folder))} photos without camera poses in {folder}: `run` poses them "
            f"first (structure from motion; its time and the stages' are not estimated until then)"
        )
        stages = [s for s in stages if s != "eval" or opt.labels is not None]  # posed photos have no labels
    else:
        try:
            report.labels = labels_dir(opt, data)
            report.scene = load_scene(data, downscale=opt.downscale, skip_missing=opt.skip_missing)
            report.ok(f"scene: {scene_size(report.scene, report.labels).describe(opt.downscale)}")
            stages = planned_stages(opt, data) if out_given else stages
        except (N2F2Error, OSError) as e:
            report.problem(f"scene: {e}")
            return stages
        stages = [s for s in stages if s != "eval" or report.labels is not None]
    skipped = [s for s in STAGES if s not in stages]
    report.ok(
        "stages: "
        + (", ".join(stages) if stages else "none")
        + " would run"
        + (f"; {', '.join(skipped)} skipped (up to date, or not asked for)" if skipped else "")
    )
    return stages


def _models(opt: RunOptions, stages: list[str], report: _Report) -> None:
    """One line per model the stages load: found (and where) or the problem with its advice."""
    from ..segments.segmenters import SEGMENTERS

    try:
        found = run_models(opt, stages)
    except N2F2Error as e:
        report.problem(f"models: {e}")
        return
    kind = SEGMENTERS.get(str(opt.segmenter))
    if "segments" in stages and opt.langsplat_features is None and kind and kind.default_model_id is None:
        report.ok(f"segmenter {opt.segmenter}: no model needed")
    for model in found:
        if model.problem:
            report.problem(model.problem)
        else:
            report.ok(model_line(model))
    if not found and "segments" not in stages:
        report.ok("models: none needed by the stages that would run")


def _machine(opt: RunOptions, report: _Report) -> None:
    """The CPU, the threads torch uses, CUDA, and whether ``--device`` is usable."""
    import torch

    from .estimate import machine_line

    report.ok(f"machine: {machine_line(opt.device)}")
    try:
        device = torch.device(opt.device)
    except (RuntimeError, ValueError) as e:
        report.problem(f"--device {opt.device}: {e}")
        return
    if device.type == "cuda" and not torch.cuda.is_available():
        report.problem(f"--device {opt.device}: CUDA is not available here; use --device cpu")
    elif device.type == "cuda" and (device.index or 0) >= torch.cuda.device_count():
        report.problem(f"--device {opt.device}: only {torch.cuda.device_count()} CUDA device(s) here")


def _estimates(opt: RunOptions, stages: list[str], report: _Report) -> None:
    """The machine's measured speed and each stage's expected time."""
    from .estimate import calibrate, scene_size, stage_estimates, total_line

    try:
        speed = calibrate(opt.device)
        size = scene_size(report.scene, report.labels)
        estimates = stage_estimates(opt, stages, size, report.scene, speed)
    except (N2F2Error, RuntimeError, ValueError) as e:  # a device torch cannot use
        report.problem(f"speed: cannot measure it on --device {opt.device} ({e})")
        return
    report.ok(f"speed: {speed.describe()}")
    for estimate in estimates:
        report.ok(estimate.line())
    if len(estimates) > 1:
        report.ok(total_line(estimates))
