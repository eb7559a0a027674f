"""Training of the bench's variants: each variant's field (the cpu preset's, shaped by the
variant) trained on the bench's data into its run folder, with its activation memory measured.
A finished run with the same settings and inputs is reused, and a shorter one with otherwise
identical settings is continued from its checkpoint.

The training-free ``lift`` variant (:func:`lift_variant`) trains nothing: it is the
``RUN/lift.pt`` that a trained run of the bench wrote from its training's blend cache, or, with no
such run (``--variants lift`` alone), the lift built here from the bench's Gaussians over the
training views the trainer would use."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping, Optional

import numpy as np

from ..io import make_dirs
from .memory import ActivationMeter, field_parameter_count, rasterized_channels
from .variants import VariantSpec, variant_field_config

if TYPE_CHECKING:
    from .config import BenchConfig, BenchData

MEMORY_NAME = "bench_memory.json"
LIFT_REPORT_NAME = "lift_report.json"


def train_variant(
    spec: VariantSpec, data: "BenchData", run_dir: Path, config: "BenchConfig", log: Callable[[str], None] = print
) -> dict:
    """Train (or reuse) one variant; returns its train report plus ``"reused"`` and ``"memory"``."""
    from ..io import write_json
    from ..pipeline.presets import get_preset
    from ..segments.bank import SegmentBank
    from ..train.checkpoint import saved_configs
    from ..train.config import CHECKPOINT_NAME, FIELD_NAME, LIFT_NAME, REPORT_NAME
    from ..train.stage import TrainJob, run_train

    field_config = variant_field_config(spec, config.dim)
    train_config = replace(
        get_preset("cpu").train,
        iterations=config.iterations,
        pixels_per_step=config.pixels_per_step,
        scale_jitter=config.scale_jitter,
        seed=config.seed,
        device=config.device,
        checkpoint_every=max(50, config.iterations // 4),
    )
    paths = {
        "scene": str(data.scene_dir.resolve()),
        "gaussians": str(data.gaussians.resolve()),
        "bank": str(data.bank_dir.resolve()),
    }
    saved = saved_configs(run_dir) if (run_dir / CHECKPOINT_NAME).is_file() else None
    inputs_ok = saved is not None and _same_inputs(run_dir, paths)
    same = inputs_ok and saved == (field_config, train_config)
    # An interrupted run (or an interrupted extension of a shorter one) has a checkpoint with
    # these settings but a field and report of fewer steps: only a finished run is reused.
    report = (
        json.loads((run_dir / REPORT_NAME).read_text())
        if same and (run_dir / FIELD_NAME).is_file() and (run_dir / REPORT_NAME).is_file()
        else None
    )
    if report is not None and report.get("steps") == train_config.iterations:
        log(f"[bench] {run_dir.name}: trained with the same settings, reused")
        memory_path = run_dir / MEMORY_NAME
        report["memory"] = json.loads(memory_path.read_text()) if memory_path.is_file() else None
        report["reused"] = True
        return report
    # A shorter run with otherwise identical settings is continued: the learning rates are
    # constant and the checkpoint holds the optimiser and sampler state, so N steps then M more
    # are the same optimisation as N + M steps at once.
    ignore = dict(iterations=0, checkpoint_every=0)
    extend = (
        inputs_ok
        and not same
        and saved is not None  # implied by inputs_ok; narrows the type of saved
        and saved[0] == field_config
        and replace(saved[1], **ignore) == replace(train_config, **ignore)
        and _checkpoint_step(run_dir) <= train_config.iterations
    )
    resume = same or extend
    if not resume:
        for stale in (CHECKPOINT_NAME, FIELD_NAME, REPORT_NAME, LIFT_NAME, MEMORY_NAME):
            (run_dir / stale).unlink(missing_ok=True)
    log(
        f"[bench] {run_dir.name}: training {spec.variant} ({spec.backbone}), D={field_config.dim}, "
        f"k={field_config.step_size}, {train_config.iterations} steps"
        + (" (resumed)" if same else " (continuing a shorter run)" if extend else "")
    )
    meter = ActivationMeter()
    job = TrainJob(
        data=data.scene_dir,
        gaussians=data.gaussians,
        bank=data.bank_dir,
        out=run_dir,
        field_config=field_config,
        train_config=train_config,
        callback=meter.end_step,
        device=config.device,
        resume=resume,
        progress=config.progress,
    )
    with meter:
        report = run_train(job, log=lambda line: log(f"[bench] {run_dir.name}: {line}"))
    bank = SegmentBank.open(data.bank_dir)
    params = field_parameter_count(field_config, int(bank.embed_dim))
    F_dim = rasterized_channels(field_config)
    memory = {
        "parameters": params,
        "parameter_mb": params * 4 / 2**20,
        # Adam keeps two moments per parameter, and the gradient is one more copy.
        "parameter_adam_grad_mb": 4 * params * 4 / 2**20,
        "activation_peak_mb": meter.peak_bytes / 2**20 if meter.steps else None,
        "activation_median_mb": float(np.median(meter.steps)) / 2**20 if meter.steps else None,
        "rasterized_channels": F_dim,
        "measured_steps": len(meter.steps),
    }
    write_json(run_dir / MEMORY_NAME, memory)
    report["memory"] = memory
    report["reused"] = False
    return report


def _checkpoint_step(run_dir: Path) -> int:
    """The step of ``run_dir``'s checkpoint (what a resumed run continues from)."""
    from ..io import load_torch
    from ..train.config import CHECKPOINT_NAME

    return int(load_torch(run_dir / CHECKPOINT_NAME)["step"])


def _same_inputs(run_dir: Path, paths: Mapping[str, str]) -> bool:
    """The run's recorded scene / bank / Gaussians are the ones of this bench."""
    from ..train.config import REPORT_NAME

    report = run_dir / REPORT_NAME
    if not report.is_file():  # an interrupted first session: the checkpoint's meta decides
        from ..io import load_torch

        try:
            ck = load_torch(run_dir / "checkpoint.pt")
            meta = ck["field_meta"]
        except Exception:  # noqa: BLE001 - unreadable: retrain
            return False
        return (
            meta.get("scene") == paths["scene"]
            and meta.get("bank") == paths["bank"]
            and meta.get("gaussians") == paths["gaussians"]
        )
    recorded = json.loads(report.read_text()).get("paths", {})
    # The trainer records the copy of the PLY inside the run; the scene and bank are compared.
    return recorded.get("scene") == paths["scene"] and recorded.get("bank") == paths["bank"]


# ------------------------------------------------------------------------------ the lift
def lift_variant(
    data: "BenchData",
    run_dir: Path,
    config: "BenchConfig",
    source: Optional[Path] = None,
    source_report: Optional[Mapping] = None,
    log: Callable[[str], None] = print,
) -> dict:
    """The training-free ``lift`` variant's "run": which lift is evaluated and what it took to
    build (also written to ``run_dir/lift_report.json``).

    ``source`` is a run trained by this bench (all of them share the Gaussians, the bank and the
    training views), ``source_report`` what :func:`train_variant` returned for it (default: its
    ``train_report.json``). When its training wrote ``source/lift.pt`` (the cpu preset's
    ``TrainConfig.lift``), that file is the lift and its build time is what the run's
    ``train_report.json`` records: the blending weights (``blend_cache.build_s``) plus the
    averaging (``lift.seconds``). Otherwise the bench builds it into ``run_dir/lift.pt``
    (:func:`n2f2.query.lifted.build_lift`: blending weights, then the lift, both timed) from
    ``source``'s Gaussians and training views, or, with no ``source``, from the bench's Gaussians
    over the training views of the cpu preset's split; a rerun reuses it while the Gaussians,
    bank, scene and views are unchanged."""
    from ..field.lift import load_lift
    from ..io import write_json

    report: dict[str, Any]
    if source is not None and source_report is None:
        source_report = _train_report(source)
    lift_info = (source_report or {}).get("lift") or {}
    if source is not None and source_report is not None and lift_info.get("written") and (source / "lift.pt").is_file():
        path = source / "lift.pt"
        lift = load_lift(path, num_gaussians=source_report.get("num_gaussians"))
        blend_s = float((source_report.get("blend_cache") or {}).get("build_s") or 0.0)
        lift_s = float(lift_info.get("seconds") or lift.seconds.get("lift", 0.0))
        log(f"[bench] {run_dir.name}: the lift {source.name}'s training wrote from its blend cache")
        report = {
            "from": "training",
            "about": f"{source.name}/lift.pt, written by its training from its cached blending weights",
            "gaussians": str(source / "gaussians.ply"),
            "reused": bool(source_report.get("reused")),
        }
    else:
        path, built, gaussians, meta = _build_lift(data, run_dir, config, source, source_report, log)
        lift = load_lift(path)
        blend_s, lift_s = float(lift.seconds.get("blend", 0.0)), float(lift.seconds.get("lift", 0.0))
        report = {
            "from": "bench",
            "about": "built by the bench: blending weights over the training views, then the lift"
            + (f" ({source.name}'s Gaussians and views; its training wrote no lift.pt)" if source else ""),
            "gaussians": gaussians,
            "reused": not built,
            "meta": meta,
        }
    report = {
        "variant": "lift",
        **report,
        "lift_path": str(path),
        "source_run": str(source) if source is not None else None,
        "views": list(lift.views),
        "num_gaussians": int(lift.features.shape[0]),
        "rule": lift.rule,
        "coverage": dict(zip(("part", "object", "group"), lift.coverage())),
        "blend_weights_s": blend_s,
        "lift_s": lift_s,
        "build_time_s": blend_s + lift_s,
    }
    make_dirs(run_dir)
    write_json(run_dir / LIFT_REPORT_NAME, report)
    return report


def _train_report(run_dir: Path) -> Optional[dict]:
    from ..train.config import REPORT_NAME

    path = run_dir / REPORT_NAME
    return json.loads(path.read_text()) if path.is_file() else None


def _build_lift(
    data: "BenchData",
    run_dir: Path,
    config: "BenchConfig",
    source: Optional[Path],
    report: Optional[Mapping],
    log: Callable[[str], None],
) -> tuple[Path, bool, str, dict]:
    """``run_dir/lift.pt`` built by :func:`n2f2.query.lifted.build_lift` under ``run_dir``'s stage
    cache: (its path, built now?, the Gaussians' PLY, the field metadata a query engine over it
    needs)."""
    from ..data import load_scene
    from ..field.lift import save_lift
    from ..gaussians import read_ply
    from ..pipeline.cache import StageCache, file_digest, scene_digest, stage_key
    from ..pipeline.presets import get_preset
    from ..query.lifted import build_lift
    from ..segments.bank import SegmentBank
    from ..train.geometry import split_views

    scene = load_scene(data.scene_dir)
    bank = SegmentBank.open(data.bank_dir)
    if source is not None and report is not None:
        ply = source / "gaussians.ply"
        views, heldout = [int(v) for v in report["train_views"]], [int(v) for v in report["heldout_views"]]
    else:  # the split of the bench's runs (the cpu preset's TrainConfig)
        ply = data.gaussians
        views, heldout = split_views(scene, get_preset("cpu").train.holdout)
    path = run_dir / "lift.pt"
    meta = {
        "encoder_spec": bank.encoder_spec,
        "scene": str(data.scene_dir.resolve()),
        "bank": str(data.bank_dir.resolve()),
        "gaussians": str(Path(ply).resolve()),
        "bank_size": [int(bank.width), int(bank.height)],
        "train_views": views,
        "heldout_views": heldout,
    }
    key = stage_key(
        gaussians=file_digest(Path(ply)),
        bank=file_digest(data.bank_dir / "bank.json"),
        scene=scene_digest(data.scene_dir),
        views=views,
    )

    def build() -> None:
        gaussians = read_ply(ply)
        lift = build_lift(gaussians, scene, bank, views, progress=config.progress)
        save_lift(path, lift, {"bank": meta["bank"], "gaussians": meta["gaussians"]})

    make_dirs(run_dir)
    built = StageCache.open(run_dir).run("lift", key, [path], build, log=lambda s: log(f"[bench] {run_dir.name}: {s}"))
    return path, built, str(ply), meta
