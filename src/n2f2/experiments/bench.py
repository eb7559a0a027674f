"""``n2f2 bench``: the paper's ablations on the built-in demo scene, in one Markdown report.

What is reproduced (paper section in brackets), all on one scene, one seed:

* composite vs explicit vs oracle querying of the N2F2 field (Table 3);
* N2F2 vs a LangSplat-like 3-level field trained on the same data (variant ``"levels"``),
  overall, split into simple / compound queries (Table 7) and per query (Table 8);
* nested vs non-nested (variant ``"flat"``; appendix "Analysis of backbone components");
* the training-free ``lift`` baseline (the bank's features averaged onto the Gaussians with the
  training views' blending weights, :mod:`n2f2.field.lift`) scored by the same query and
  evaluation code, beside every field, with the time to build each: a field's training seconds,
  the lift's blending weights plus averaging;
* the step size k of the dimension-scale mapping (Table 6; see :mod:`.variants`);
* TriPlane+MLP vs MLP backbone: convergence and memory (appendix, same section);
* the query-time breakdown (Table 4);
* the temperature ``T`` of the composite weights ``gamma = softmax(score / T)`` (``T = 1`` is
  the paper and the bench's composite rows; ``T = inf`` gives the plain mean of the scale
  features; gamma's statistics are reported at each ``T``), and composite with n2f2's default
  weights, the mean of the normalised scale features, in a row of its own.

Flow. The scene, fitted Gaussians and segment bank are built once under ``OUT/data/`` (or
given) by the pipeline's stages under its stage cache; every variant is trained into
``OUT/runs/<run>/`` (:mod:`.training`; the lift's report and evaluation go to ``OUT/runs/lift/``),
evaluated by :func:`n2f2.eval.runner.evaluate_run` (LangSplat's protocol, both box sizes), by
:func:`n2f2.eval.protocol3d.evaluate_protocol3d` (the 3D protocol: Gaussians selected by text,
the selection rendered into each labelled view; every 3D mode of each run, the lift included,
into ``OUT/runs/<run>/eval3d/``) and by :func:`n2f2.train.evaluate.evaluate_cosine_by_level`
(:mod:`.evaluate`), and the numbers are collected into ``OUT/bench.json``, ``OUT/bench.md`` and
a few PNG plots (:mod:`.report`). A rerun resumes: a run trained with the same configs on the
same data is not retrained, and an evaluation of an unchanged field is not redone.

Nothing here re-implements training, relevancy or the protocol; the claims' verdicts
(:mod:`.claims`) are computed from the evaluation results with a paired standard error over
(frame, query) pairs so that a difference within noise is called so.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any, Callable, Mapping, Optional, Sequence, Union

from ..errors import InputError
from ..pipeline.presets import get_preset
from ..pipeline.run import DemoScene
from ..query.modes import QUERY_MODES
from .claims import PAPER_RENDER, UNIT, tag
from .config import BenchConfig, BenchData
from .variants import VARIANTS, run_name, scaled_step

_CPU = get_preset("cpu")  # the defaults the bench shares with `n2f2 run`


# ------------------------------------------------------------------------------ data
def prepare_data(
    out: Path,
    config: BenchConfig,
    scene: Optional[Union[str, Path]] = None,
    gaussians: Optional[Union[str, Path]] = None,
    bank: Optional[Union[str, Path]] = None,
    log: Callable[[str], None] = print,
) -> BenchData:
    """Generate the demo scene, fit its Gaussians (the cpu preset sized to the scene) and build
    its segment bank (ground-truth segments, caption embeddings) under ``out/data`` unless given,
    each with the pipeline's stages under the stage cache of ``out/data``."""
    from ..gaussians.stage import FitJob, run_fit
    from ..io import make_dirs
    from ..pipeline.cache import StageCache, file_digest, scene_digest, stage_key, tree_digest
    from ..pipeline.run import cached_demo_scene
    from ..segments.stage import BankJob, run_bank

    data = out / "data"
    make_dirs(data)
    cache = StageCache.open(data)
    built: dict[str, bool] = {}
    seconds: dict[str, float] = {}

    t0 = time.perf_counter()
    if scene is None:
        scene_dir = data / "scene"
        spec = DemoScene(
            views=config.scene_views, width=config.scene_width, height=config.scene_height, seed=config.seed
        )
        built["scene"] = cached_demo_scene(cache, scene_dir, spec, progress=config.progress, log=log)
    else:
        scene_dir = Path(scene)
        built["scene"] = False
    seconds["scene"] = time.perf_counter() - t0
    if not scene_dir.is_dir():
        raise InputError(scene_dir, "scene folder does not exist")
    if not (scene_dir / "regions.json").is_file():
        raise InputError(
            scene_dir,
            "the bench needs the built-in demo scene (regions.json with ground-truth "
            "regions and captions); generate one with `n2f2 demo --scene-only`",
        )
    label_dir = scene_dir / "label"
    if not label_dir.is_dir():
        raise InputError(label_dir, "the scene has no LangSplat labels (label/frame_*.json)")
    sdig = scene_digest(scene_dir)

    t0 = time.perf_counter()
    if gaussians is not None:
        ply = Path(gaussians)
        ply = ply / "gaussians.ply" if ply.is_dir() else ply
        if not ply.is_file():
            raise InputError(ply, "Gaussians file does not exist")
        built["gaussians"] = False
    else:
        fit_dir = data / "gaussians"
        ply = fit_dir / "gaussians.ply"
        key = stage_key(scene=sdig, preset="cpu", steps=config.fit_steps, seed=config.seed)
        built["gaussians"] = cache.run(
            "fit-gaussians",
            key,
            [ply],
            lambda: run_fit(
                FitJob(
                    scene_dir,
                    fit_dir,
                    preset=_CPU.name,
                    overrides={} if config.fit_steps is None else {"steps": config.fit_steps},
                    seed=config.seed,
                    device=config.device,
                    force=True,
                    progress=config.progress,
                ),
                log=log,
            ),
            log,
        )
    seconds["gaussians"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if bank is not None:
        bank_dir = Path(bank)
        if not (bank_dir / "bank.json").is_file():
            raise InputError(bank_dir, "not a segment bank (no bank.json)")
        built["bank"] = False
    else:
        bank_dir = data / "bank"
        key = stage_key(
            scene=sdig,
            regions=tree_digest(scene_dir, ("regions.json", "regions/*")),
            gaussians=file_digest(ply),
            segmenter="ground-truth",
            encoder="captions",
            scale_measure=config.scale_measure,
        )

        def build() -> None:
            if bank_dir.exists():  # other inputs: a resumed bank would mix them
                shutil.rmtree(bank_dir)
            job = BankJob(
                scene_dir,
                bank_dir,
                ply,
                segmenter="ground-truth",
                encoder="captions",
                lift=replace(_CPU.lift, scale_measure=config.scale_measure),
                device=config.device,
                force=True,
                progress=config.progress,
            )
            run_bank(job, log=log)

        built["bank"] = cache.run("segments", key, [bank_dir / "bank.json"], build, log)
    seconds["bank"] = time.perf_counter() - t0
    return BenchData(scene_dir, ply, bank_dir, label_dir, built, seconds)


# ------------------------------------------------------------------------------ the bench
def run_bench(
    out: Union[str, Path],
    config: Optional[BenchConfig] = None,
    *,
    scene: Optional[Union[str, Path]] = None,
    gaussians: Optional[Union[str, Path]] = None,
    bank: Optional[Union[str, Path]] = None,
    log: Callable[[str], None] = print,
) -> dict:
    """Run every requested variant (see the module docstring); writes ``OUT/bench.json``,
    ``OUT/bench.md`` and ``OUT/*.png`` and returns the bench.json content."""
    from ..io import claim_out_dir, write_json, write_text
    from .claims import evaluate_claims
    from .evaluate import MemoEncoder
    from .report import markdown_bench, method_rows, protocol3d_rows, write_plots

    config = config or BenchConfig()
    out = Path(out)
    claim_out_dir(out, ())
    t_start = time.perf_counter()
    load_start = os.getloadavg()
    stage_s: dict[str, float] = {}

    data = prepare_data(out, config, scene=scene, gaussians=gaussians, bank=bank, log=log)
    stage_s.update({f"data: {k}": v for k, v in data.seconds.items()})
    from ..segments.bank import SegmentBank
    from ..segments.encoders import get_encoder

    # One text encoder for every evaluation (each engine would load its own and re-encode).
    encoder = MemoEncoder(get_encoder(SegmentBank.open(data.bank_dir).encoder_spec, device=config.device))

    runs, variant_runs = _train_variants(out, config, data, log, stage_s)
    _build_lifts(out, config, data, runs, variant_runs, log, stage_s)
    _evaluate_runs(out, config, data, runs, variant_runs, encoder, log, stage_s)
    gamma = _temperature_sweep(out, config, data, runs, variant_runs, encoder, log, stage_s)
    main_name = variant_runs.get("nested")

    paper_params = None
    if "mlp" in variant_runs and main_name is not None:
        from ..field import FieldConfig
        from .memory import field_parameter_count

        E = int(encoder_dim(data))
        paper_params = {b: field_parameter_count(FieldConfig.paper(backbone=b), E) for b in ("triplane", "mlp")}

    timing = None
    if main_name is not None:
        from .timing import timing_breakdown

        t0 = time.perf_counter()
        log("[bench] timing breakdown (Table 4)")
        levels_dir = out / "runs" / variant_runs["levels"] if "levels" in variant_runs else None
        timing = timing_breakdown(out / "runs" / main_name, levels_dir, data, config, encoder)
        stage_s["timing"] = time.perf_counter() - t0

    result = _bench_result(config, data, runs, variant_runs, gamma, timing, paper_params, stage_s, load_start)
    result["claims"] = evaluate_claims(result, runs, variant_runs)
    result["methods"] = method_rows(result, runs, variant_runs)
    result["protocol3d"] = protocol3d_rows(runs)
    result["seconds"] = time.perf_counter() - t_start
    plots = write_plots(out, result, runs, variant_runs)
    result["plots"] = {k: str(v) for k, v in plots.items()}
    write_text(out / "bench.md", markdown_bench(result, runs, variant_runs))
    write_json(out / "bench.json", {**result, "evals": {n: e["evals"] for n, e in runs.items()}})
    log(f"[bench] done in {result['seconds']:.0f} s -> {out / 'bench.md'}")
    return result


def _train_variants(
    out: Path, config: BenchConfig, data: BenchData, log: Callable[[str], None], stage_s: dict[str, float]
) -> tuple[dict[str, dict], dict[str, str]]:
    """(run name -> its entry, variant -> run name): one entry per run of the requested
    variants (variants sharing a run share the entry), each field trained into ``OUT/runs/``."""
    from .training import train_variant

    specs = [VARIANTS[v] for v in config.variants]
    runs: dict[str, dict] = {}  # run name -> {"train", "evals", "cosine"}
    variant_runs: dict[str, str] = {}
    for spec in specs:
        name = run_name(spec, config.dim)
        variant_runs[spec.name] = name
        run_dir = out / "runs" / name
        entry = runs.setdefault(
            name,
            {
                "evals": {},
                "cosine": None,
                "modes": [],
                "cosine_wanted": False,
                "variant": spec.name if spec.training_free else spec.variant,
                "backbone": None if spec.training_free else spec.backbone,
                "training_free": spec.training_free,
            },
        )
        entry["modes"] = list(dict.fromkeys(entry["modes"] + list(spec.modes)))
        entry["cosine_wanted"] |= spec.cosine
        if "train" not in entry and not spec.training_free:
            t0 = time.perf_counter()
            entry["train"] = train_variant(spec, data, run_dir, config, log)
            stage_s[f"train {name}"] = time.perf_counter() - t0
    return runs, variant_runs


def _build_lifts(
    out: Path,
    config: BenchConfig,
    data: BenchData,
    runs: dict[str, dict],
    variant_runs: Mapping[str, str],
    log: Callable[[str], None],
    stage_s: dict[str, float],
) -> None:
    """The training-free runs, after the fields: a trained run's training writes the lift from
    its blend cache."""
    from .training import lift_variant

    for name, entry in runs.items():
        if entry["training_free"]:
            source = _lift_source(runs, variant_runs)
            t0 = time.perf_counter()
            entry["train"] = lift_variant(
                data,
                out / "runs" / name,
                config,
                out / "runs" / source if source else None,
                runs[source]["train"] if source else None,
                log,
            )
            stage_s[f"build {name}"] = time.perf_counter() - t0


def _evaluate_runs(
    out: Path,
    config: BenchConfig,
    data: BenchData,
    runs: dict[str, dict],
    variant_runs: Mapping[str, str],
    encoder: Any,
    log: Callable[[str], None],
    stage_s: dict[str, float],
) -> None:
    """Every run's 2D evaluation (the N2F2 run's also with the paper's test-time rendering),
    held-out cosines where wanted, and 3D evaluation, into its entry."""
    from .evaluate import cosine_variant, evaluate_lift, evaluate_lift_3d, evaluate_variant, evaluate_variant_3d

    for name, entry in runs.items():
        run_dir = out / "runs" / name
        t0 = time.perf_counter()
        modes = _mode_order(entry["modes"])
        if entry["training_free"]:
            entry["evals"]["T1"] = evaluate_lift(
                run_dir, entry["train"], data, modes, run_dir / "eval", config, log, encoder
            )
            stage_s[f"eval {name}"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            entry["eval3d"] = evaluate_lift_3d(run_dir, entry["train"], data, run_dir / "eval3d", config, log, encoder)
            stage_s[f"eval 3D {name}"] = time.perf_counter() - t0
            continue
        entry["evals"]["T1"] = evaluate_variant(run_dir, data, modes, run_dir / "eval", config, 1.0, log, encoder)
        if name == variant_runs.get("nested"):  # the paper's test-time rendering beside the default
            paper_modes = [m for m in modes if QUERY_MODES[m].paper and not QUERY_MODES[m].needs_truth]
            entry["evals"][PAPER_RENDER] = evaluate_variant(
                run_dir, data, paper_modes, run_dir / "eval_gaussians", config, 1.0, log, encoder, render="gaussians"
            )
        if entry["cosine_wanted"]:
            entry["cosine"] = cosine_variant(run_dir, data, config, log)
        stage_s[f"eval {name}"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        entry["eval3d"] = evaluate_variant_3d(run_dir, data, run_dir / "eval3d", config, log, encoder)
        stage_s[f"eval 3D {name}"] = time.perf_counter() - t0


def _temperature_sweep(
    out: Path,
    config: BenchConfig,
    data: BenchData,
    runs: dict[str, dict],
    variant_runs: Mapping[str, str],
    encoder: Any,
    log: Callable[[str], None],
    stage_s: dict[str, float],
) -> list[dict]:
    """Composite's temperature on the k = 1 nested TriPlane run: gamma's statistics at each
    temperature, composite evaluated at each one but T = 1 (already done) and with n2f2's
    default weights; nothing without that run."""
    from .evaluate import evaluate_variant, gamma_statistics

    gamma: list[dict] = []
    main_name = variant_runs.get("nested")
    if main_name is not None:
        from ..query.engine import QueryConfig, QueryEngine

        t0 = time.perf_counter()
        main_dir = out / "runs" / main_name
        for T in config.temperatures:
            engine = QueryEngine.from_run(
                main_dir, device=config.device, scene=data.scene_dir, config=QueryConfig(temperature=T), encoder=encoder
            )
            gamma.append(gamma_statistics(engine, T))
            if T != 1.0:
                runs[main_name]["evals"][tag(T)] = evaluate_variant(
                    main_dir, data, ["composite"], main_dir / f"eval_{tag(T)}", config, T, log, encoder
                )
        # n2f2's default composite weights (the mean of the normalised scale features) beside Eq. 6's.
        runs[main_name]["evals"][UNIT] = evaluate_variant(
            main_dir, data, ["composite"], main_dir / f"eval_{UNIT}", config, 1.0, log, encoder, weights="unit"
        )
        stage_s["temperature"] = time.perf_counter() - t0
    return gamma


def _bench_result(
    config: BenchConfig,
    data: BenchData,
    runs: Mapping[str, dict],
    variant_runs: dict[str, str],
    gamma: list[dict],
    timing: Optional[dict],
    paper_params: Optional[dict],
    stage_s: dict[str, float],
    load_start: Sequence[float],
) -> dict:
    """``bench.json``'s content before the claims, methods, 3D rows, seconds and plots."""
    from ..query.composite import temperature_name

    return {
        "format": "n2f2-bench-v1",
        # JSON has no infinity: the uniform temperature is recorded by its name (query/composite.py).
        "config": {**asdict(config), "temperatures": [temperature_name(T) for T in config.temperatures]},
        "data": {
            "scene": str(data.scene_dir),
            "gaussians": str(data.gaussians),
            "bank": str(data.bank_dir),
            "labels": str(data.label_dir),
            "built": data.built,
            # what the bank was built with (a given --bank need not match config.scale_measure)
            "scale_measure": json.loads((data.bank_dir / "bank.json").read_text())["lifting"].get(
                "scale_measure", "eigenvalue"
            ),
        },
        "environment": _environment(),
        "variant_runs": variant_runs,
        "steps": {
            name: scaled_step(VARIANTS[v].paper_step, config.dim)
            for v, name in variant_runs.items()
            if VARIANTS[v].kind.uses_step
        },
        "runs": {name: _run_summary(entry) for name, entry in runs.items()},
        "gamma": gamma,
        "timing": timing,
        "paper_size_parameters": paper_params,
        "stage_seconds": stage_s,
        "load_average": {"start": list(load_start), "end": list(os.getloadavg())},
    }


def encoder_dim(data: BenchData) -> int:
    """E, the teacher embedding size of the bank."""
    from ..segments.bank import SegmentBank

    return int(SegmentBank.open(data.bank_dir).embed_dim)


def _lift_source(runs: Mapping[str, dict], variant_runs: Mapping[str, str]) -> Optional[str]:
    """The trained run whose ``lift.pt`` the lift variant uses: the N2F2 run, else the first run
    trained (every run of the bench has the same Gaussians, bank and training views); None when
    the bench trains nothing."""
    nested = variant_runs.get("nested")
    if nested is not None:
        return nested
    return next((name for name, entry in runs.items() if not entry["training_free"]), None)


def _mode_order(modes: Sequence[str]) -> list[str]:
    from ..query.engine import MODES

    return [m for m in MODES if m in modes]


def _environment() -> dict:
    import platform

    import torch

    return {
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "machine": platform.machine(),
    }


def _run_summary(entry: Mapping) -> dict:
    """A run's line of ``bench.json``; ``build_time_s``: a field's training seconds, the lift's
    blending weights plus averaging (``lift``: where it came from)."""
    t = entry["train"]
    summary = {
        "variant": entry["variant"],
        "backbone": entry["backbone"],
        "field_config": t.get("field_config"),
        "train_config": t.get("train_config"),
        "steps": t.get("steps"),
        "final_loss": t.get("final_loss"),
        "train_time_s": t.get("train_time_s"),
        "time_per_iteration_s": t.get("time_per_iteration_s"),
        "cpu_time_per_iteration_s": t.get("cpu_time_per_iteration_s"),
        "reused": t.get("reused"),
        "num_gaussians": t.get("num_gaussians"),
        "memory": t.get("memory"),
        "curve": t.get("curve"),
        "cosine": entry.get("cosine"),
        "evals": sorted(entry["evals"]),
        "training_free": entry["training_free"],
        "build_time_s": t.get("build_time_s", t.get("train_time_s")),
        "blend_cache_s": (t.get("blend_cache") or {}).get("build_s"),  # a field's precomputed blending weights
    }
    if entry["training_free"]:
        keys = ("from", "about", "lift_path", "source_run", "gaussians", "views", "rule", "coverage")
        summary["lift"] = {k: t.get(k) for k in keys + ("blend_weights_s", "lift_s")}
    return summary
