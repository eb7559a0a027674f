"""Training of the bench's variants: each variant's field (the cpu preset's, shaped by the
variant) trained on the bench's data into its run folder, with its activation memory measured.
A finished run with the same settings and inputs is reused, and a shorter one with otherwise
identical settings is continued from its checkpoint."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Mapping

import numpy as np

from .memory import ActivationMeter, field_parameter_count, rasterized_channels
from .variants import VariantSpec, variant_field_config

if TYPE_CHECKING:
    from .bench import BenchConfig, BenchData

MEMORY_NAME = "bench_memory.json"


def train_variant(
    spec: VariantSpec, data: "BenchData", run_dir: Path, config: "BenchConfig", log: Callable[[str], None] = print
) -> dict:
    """Train (or reuse) one variant; returns its train report plus ``"reused"`` and ``"memory"``."""
    from ..data import load_scene
    from ..gaussians import read_ply
    from ..io import write_json
    from ..pipeline.presets import get_preset
    from ..segments.bank import SegmentBank
    from ..train.trainer import CHECKPOINT_NAME, FIELD_NAME, REPORT_NAME, saved_configs, train_field

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
        for stale in (CHECKPOINT_NAME, FIELD_NAME, REPORT_NAME, MEMORY_NAME):
            (run_dir / stale).unlink(missing_ok=True)
    log(
        f"[bench] {run_dir.name}: training {spec.variant} ({spec.backbone}), D={field_config.dim}, "
        f"k={field_config.step_size}, {train_config.iterations} steps"
        + (" (resumed)" if same else " (continuing a shorter run)" if extend else "")
    )
    scene = load_scene(data.scene_dir)
    bank = SegmentBank.open(data.bank_dir)
    gaussians = read_ply(data.gaussians)
    meter = ActivationMeter()
    with meter:
        report = train_field(
            scene,
            gaussians,
            bank,
            run_dir,
            field_config=field_config,
            config=train_config,
            resume=resume,
            paths=paths,
            progress=config.progress,
            callback=meter.end_step,
        )
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
    from ..train.trainer import CHECKPOINT_NAME

    return int(load_torch(run_dir / CHECKPOINT_NAME)["step"])


def _same_inputs(run_dir: Path, paths: Mapping[str, str]) -> bool:
    """The run's recorded scene / bank / Gaussians are the ones of this bench."""
    from ..train.trainer import REPORT_NAME

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
