"""``n2f2 bench``: the paper's ablations on the built-in demo scene, in one Markdown report.

What is reproduced (paper section in brackets), all on one scene, one seed:

* composite vs explicit vs oracle querying of the N2F2 field (Table 3);
* N2F2 vs a LangSplat-like 3-level field trained on the same data (variant ``"levels"``),
  overall, split into simple / compound queries (Table 7) and per query (Table 8);
* nested vs non-nested (variant ``"flat"``; appendix "Analysis of backbone components");
* the step size k of the dimension-scale mapping (Table 6);
* TriPlane+MLP vs MLP backbone: convergence and memory (appendix, same section);
* the query-time breakdown (Table 4);
* the temperature ``T`` of the composite weights ``gamma = softmax(score / T)`` (``T = 1`` is
  the paper; at ``T = 1`` gamma is close to uniform, so its statistics are reported).

Flow. The scene, fitted Gaussians and segment bank are built once under ``OUT/data/`` (or
given), every variant is trained into ``OUT/runs/<run>/`` by :func:`n2f2.train.train_field`,
evaluated by :func:`n2f2.eval.runner.evaluate_run` (LangSplat's protocol, both box sizes) and by
:func:`n2f2.train.evaluate.evaluate_cosine_by_level`, and the numbers are collected into
``OUT/bench.json``, ``OUT/bench.md`` and a few PNG plots. A rerun resumes: a run whose
``field.pt`` was trained with the same configs on the same data is not retrained, and an
evaluation whose ``eval.json`` is newer than the field is not redone.

Step size and D. The paper uses D = 512 and k in {1, 8, 32, 128, 170}. With a smaller D the bench
keeps the *number of scales* ``floor(512 / k)`` of each paper setting: ``k_used =
max(1, floor(D / floor(512 / k)))`` (:func:`scaled_step`); at D = 128 that is k in {1, 2, 8, 32, 42}
(= round(k D / 512), with k = 170 -> 42 so that it keeps its 3 scales). The report states the
mapping.

Nothing here re-implements training, relevancy or the protocol; the claims' verdicts are computed
from the evaluation results with a paired standard error over (frame, query) pairs so that a
difference within noise is called so.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import shutil
import time
from dataclasses import asdict, dataclass, field as dc_field, replace
from pathlib import Path
from typing import Any, Callable, Mapping, Optional, Sequence, Union

import numpy as np

from ..errors import InputError
from ..segments.lifting import SCALE_MEASURES
from ..validate import OneLineArgumentParser, nonneg_float, positive_float, positive_int

PAPER_DIM = 512
PAPER_STEPS = (1, 8, 32, 128, 170)  # paper Table 6
BOXES = ("exact", "scaled")
DATA_KEY_NAME = "bank_key.json"
MEMORY_NAME = "bench_memory.json"
TEMPERATURES = (1.0, 0.1, 0.01)  # 1 = paper


# ------------------------------------------------------------------------------ variants
@dataclass(frozen=True)
class VariantSpec:
    """One bench variant: a field configuration and what to evaluate on it."""

    name: str  # user-facing name (--variants)
    title: str  # row label in the report
    variant: str  # FieldConfig.variant: nested | flat | levels
    backbone: str = "triplane"  # FieldConfig.backbone
    paper_step: int = 1  # k of paper Table 6 (scaled to D by scaled_step)
    modes: tuple[str, ...] = ("composite", "explicit", "oracle")
    cosine: bool = True  # per-level cosine to the teacher on held-out views


VARIANTS: dict[str, VariantSpec] = {
    "nested": VariantSpec("nested", "N2F2 (nested, TriPlane+MLP, k=1)", "nested"),
    "flat": VariantSpec("flat", "non-nested (flat)", "flat"),
    "levels": VariantSpec("levels", "3-level (LangSplat-like)", "levels", modes=("levels", "oracle")),
    **{f"k{k}": VariantSpec(f"k{k}", f"N2F2, k={k}", "nested", paper_step=k, cosine=False)
       for k in PAPER_STEPS[1:]},
    "mlp": VariantSpec("mlp", "N2F2 with MLP backbone (PE+MLP)", "nested", backbone="mlp", modes=("composite",)),
}
DEFAULT_VARIANTS = tuple(VARIANTS)


def scaled_step(paper_k: int, dim: int) -> int:
    """The step size at ``dim`` dimensions that keeps paper setting ``paper_k``'s number of scales
    ``floor(512 / paper_k)`` (at least 1, at most ``dim``)."""
    if paper_k < 1 or paper_k > PAPER_DIM:
        raise ValueError(f"paper step size must be in [1, {PAPER_DIM}], got {paper_k}")
    if dim == PAPER_DIM:
        return paper_k
    return int(min(dim, max(1, dim // (PAPER_DIM // paper_k))))


def run_name(spec: VariantSpec, dim: int) -> str:
    """Run folder of a variant, named by what is trained (paper k values that map to the same
    k at this D share one run)."""
    if spec.variant != "nested":
        return spec.variant + ("" if spec.backbone == "triplane" else f"-{spec.backbone}")
    k = scaled_step(spec.paper_step, dim)
    return f"nested-k{k}" + ("" if spec.backbone == "triplane" else f"-{spec.backbone}")


# ------------------------------------------------------------------------------ config
@dataclass
class BenchConfig:
    """Settings of :func:`run_bench`. Defaults: the full bench on the default demo scene, sized to
    finish in about 30 minutes on 2 CPU cores once the Gaussians exist (see :meth:`quick`)."""

    iterations: int = 1000  # training steps per variant (TrainConfig.cpu() has 3000; 1000 keeps ~30 min)
    dim: int = 128  # D of every field (paper 512; k is scaled to keep the number of scales)
    pixels_per_step: int = 4096
    # The demo pipeline's (cpu preset) departures from the paper; "eigenvalue" and 0.0 are the
    # paper's. See LiftSettings.scale_measure and TrainConfig.scale_jitter.
    scale_measure: str = "extent"
    scale_jitter: float = 0.03
    variants: tuple[str, ...] = DEFAULT_VARIANTS
    temperatures: tuple[float, ...] = TEMPERATURES  # composite T evaluated on the k=1 nested run
    timing_repeats: int = 5  # medians over this many repeats in the timing breakdown
    timing_threads: int = 1  # torch threads while timing (1: stable on a shared 2-core machine)
    # Scene generated when none is given (the default demo scene), and its Gaussian fit.
    scene_views: int = 40
    scene_width: int = 160
    scene_height: int = 120
    fit_steps: Optional[int] = None  # None: FitConfig.cpu()'s
    seed: int = 0
    device: str = "cpu"
    progress: bool = True

    def __post_init__(self) -> None:
        unknown = [v for v in self.variants if v not in VARIANTS]
        if unknown:
            raise ValueError(f"unknown variant(s) {unknown}; choose from {list(VARIANTS)}")
        if self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        if self.dim < 3:
            raise ValueError(f"dim must be >= 3, got {self.dim}")
        if self.scale_measure not in SCALE_MEASURES:
            raise ValueError(f"scale_measure must be one of {SCALE_MEASURES}, got {self.scale_measure!r}")
        if not 0.0 <= self.scale_jitter < 1.0:
            raise ValueError(f"scale_jitter must be in [0, 1), got {self.scale_jitter}")
        if not self.temperatures or any(not t > 0 for t in self.temperatures):
            raise ValueError(f"temperatures must be positive, got {self.temperatures}")
        self.variants = tuple(dict.fromkeys(self.variants))
        self.temperatures = tuple(dict.fromkeys(float(t) for t in self.temperatures))

    @staticmethod
    def quick(**overrides: Any) -> "BenchConfig":
        """A few minutes: small generated scene, D = 32, short training, fewer timing repeats."""
        base = dict(iterations=150, dim=32, pixels_per_step=2048, timing_repeats=2, scene_views=16,
                    scene_width=96, scene_height=72, fit_steps=300)
        base.update(overrides)
        return BenchConfig(**base)


@dataclass
class BenchData:
    """The scene, Gaussians and segment bank every variant trains on."""

    scene_dir: Path
    gaussians: Path
    bank_dir: Path
    label_dir: Path
    built: dict[str, bool] = dc_field(default_factory=dict)  # stage -> built now (False: reused)
    seconds: dict[str, float] = dc_field(default_factory=dict)


# ------------------------------------------------------------------------------ data
def prepare_data(out: Path, config: BenchConfig, scene: Optional[Union[str, Path]] = None,
                 gaussians: Optional[Union[str, Path]] = None,
                 bank: Optional[Union[str, Path]] = None, log: Callable[[str], None] = print) -> BenchData:
    """Generate the demo scene, fit its Gaussians and build its segment bank (ground-truth
    segments, caption embeddings) under ``out/data`` unless given; each is reused when present."""
    from ..pipeline import file_digest

    data = out / "data"
    built: dict[str, bool] = {}
    seconds: dict[str, float] = {}

    scene_dir = Path(scene) if scene is not None else data / "scene"
    t0 = time.perf_counter()
    if scene is None and not (scene_dir / "scene.json").is_file():
        from ..data.synthetic import generate_demo_scene

        log(f"[bench] generating the demo scene -> {scene_dir}")
        generate_demo_scene(scene_dir, num_views=config.scene_views, width=config.scene_width,
                            height=config.scene_height, seed=config.seed, show_progress=config.progress)
        built["scene"] = True
    else:
        built["scene"] = False
    seconds["scene"] = time.perf_counter() - t0
    if not scene_dir.is_dir():
        raise InputError(scene_dir, "scene folder does not exist")
    if not (scene_dir / "regions.json").is_file():
        raise InputError(scene_dir, "the bench needs the built-in demo scene (regions.json with ground-truth "
                                    "regions and captions); generate one with `n2f2 demo --scene-only`")
    label_dir = scene_dir / "label"
    if not label_dir.is_dir():
        raise InputError(label_dir, "the scene has no LangSplat labels (label/frame_*.json)")

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
        built["gaussians"] = not ply.is_file()
        if built["gaussians"]:
            from ..data import load_scene
            from ..gaussians.fit import CHECKPOINT_NAME, FitConfig, fit_gaussians

            scene = load_scene(scene_dir)
            # the cpu preset sized to the scene, as fit-gaussians does (fit_steps keeps its fractions)
            fit_config = replace(FitConfig.cpu().sized_for(scene, steps=config.fit_steps or None),
                                 seed=config.seed, device=config.device)
            log(f"[bench] fitting Gaussians ({fit_config.steps} steps) -> {fit_dir}")
            fit_gaussians(scene, fit_config, fit_dir,
                          resume=(fit_dir / CHECKPOINT_NAME).is_file(), progress=config.progress)
    seconds["gaussians"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    if bank is not None:
        bank_dir = Path(bank)
        if not (bank_dir / "bank.json").is_file():
            raise InputError(bank_dir, "not a segment bank (no bank.json)")
        built["bank"] = False
    else:
        bank_dir = data / "bank"
        key = {"scene": str(scene_dir.resolve()), "gaussians": file_digest(ply),
               "segmenter": "ground-truth", "encoder": "captions", "scale_measure": config.scale_measure}
        key_path = data / DATA_KEY_NAME
        recorded = json.loads(key_path.read_text()) if key_path.is_file() else None
        built["bank"] = not ((bank_dir / "bank.json").is_file() and recorded == key)
        if built["bank"]:
            from ..data import load_scene
            from ..gaussians import read_ply
            from ..io import write_json
            from ..segments.bank import SegmentAndEncode, build_bank
            from ..segments.encoders import get_encoder
            from ..segments.lifting import LiftSettings, render_depth_provider
            from ..segments.segmenters import get_segmenter

            if bank_dir.exists() and recorded != key:  # other inputs: a resumed bank would mix them
                shutil.rmtree(bank_dir)
            log(f"[bench] building the segment bank (ground-truth segments, caption embeddings) -> {bank_dir}")
            scene_obj = load_scene(scene_dir)
            depth = render_depth_provider(read_ply(ply, device=config.device), scene_obj.cameras,
                                          min_alpha=LiftSettings().min_alpha)
            source = SegmentAndEncode(get_segmenter("ground-truth", scene=scene_obj),
                                      get_encoder("captions", device=config.device))
            build_bank(scene_obj, source, depth, bank_dir, lift=LiftSettings(scale_measure=config.scale_measure),
                       progress=config.progress)
            write_json(key_path, key)
    seconds["bank"] = time.perf_counter() - t0
    return BenchData(scene_dir, ply, bank_dir, label_dir, built, seconds)


class MemoEncoder:
    """A text encoder that remembers its embeddings, shared by the bench's many query engines
    (queries, negatives and canonical phrases are the same in every evaluation)."""

    def __init__(self, encoder: Any) -> None:
        self._encoder = encoder
        self._cache: dict[str, Any] = {}

    def __getattr__(self, name: str) -> Any:  # description, spec, name, ... of the wrapped encoder
        return getattr(self._encoder, name)

    def encode_text(self, texts: Sequence[str]) -> Any:  # -> [Q, E]
        import torch

        missing = [t for t in dict.fromkeys(texts) if t not in self._cache]
        if missing:
            for t, e in zip(missing, torch.as_tensor(self._encoder.encode_text(list(missing)))):
                self._cache[t] = e
        return torch.stack([self._cache[t] for t in texts])


# ------------------------------------------------------------------------------ memory
class ActivationMeter:
    """Bytes of the tensors autograd saves for backward, per optimisation step (the activation
    memory of training), measured with ``torch.autograd.graph.saved_tensors_hooks``.

    Storages are counted once per step; storages of ``exclude`` tensors (the parameters) are not
    activations and are skipped. :meth:`end_step` closes a step (called from the trainer's
    per-step callback)."""

    def __init__(self, exclude: Sequence[Any] = ()) -> None:
        self._exclude = {self._key(t) for t in exclude}
        self._seen: set = set()
        self._bytes = 0
        self.steps: list[int] = []
        self._ctx = None

    @staticmethod
    def _key(t: Any) -> int:
        return t.untyped_storage().data_ptr()

    def _pack(self, t: Any) -> Any:
        try:
            key = self._key(t)
        except (RuntimeError, NotImplementedError):  # e.g. tensors without a storage
            return t
        if key not in self._exclude and key not in self._seen:
            self._seen.add(key)
            self._bytes += t.untyped_storage().nbytes()
        return t

    def end_step(self, *_: Any) -> None:
        self.steps.append(self._bytes)
        self._seen.clear()
        self._bytes = 0

    @property
    def peak_bytes(self) -> int:
        return max(self.steps + [self._bytes])

    def __enter__(self) -> "ActivationMeter":
        import torch

        self._ctx = torch.autograd.graph.saved_tensors_hooks(self._pack, lambda t: t)
        self._ctx.__enter__()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._ctx.__exit__(*exc)


def parameter_bytes(module: Any) -> int:
    """Bytes of a module's trainable parameters."""
    return int(sum(p.numel() * p.element_size() for p in module.parameters() if p.requires_grad))


def field_parameter_count(config: Any, embed_dim: int) -> int:
    """Trainable parameters of a field with ``config`` (built once per config and dropped: the
    paper-size TriPlane is ~200 MB for a moment). The variant and k do not change the count."""
    from ..field.model import FieldConfig

    shape = FieldConfig.from_dict({**config.to_dict(), "variant": "nested", "step_size": 1})
    return _parameter_count(json.dumps(shape.to_dict(), sort_keys=True), int(embed_dim))


@functools.lru_cache(maxsize=None)
def _parameter_count(config_json: str, embed_dim: int) -> int:
    from ..field.model import FieldConfig, NestedField

    field = NestedField(FieldConfig.from_dict(json.loads(config_json)), embed_dim, np.zeros(3), np.ones(3))
    return int(sum(p.numel() for p in field.parameters() if p.requires_grad))


# ------------------------------------------------------------------------------ training
def train_variant(spec: VariantSpec, data: BenchData, run_dir: Path, config: BenchConfig,
                  log: Callable[[str], None] = print) -> dict:
    """Train (or reuse) one variant; returns its train report plus ``"reused"`` and ``"memory"``."""
    from ..data import load_scene
    from ..field import FieldConfig
    from ..gaussians import read_ply
    from ..io import write_json
    from ..segments.bank import SegmentBank
    from ..train.trainer import (CHECKPOINT_NAME, FIELD_NAME, REPORT_NAME, TrainConfig, saved_configs,
                                 train_field)

    field_config = FieldConfig(dim=config.dim, variant=spec.variant, backbone=spec.backbone,
                               step_size=scaled_step(spec.paper_step, config.dim) if spec.variant == "nested" else 1)
    train_config = replace(TrainConfig.cpu(), iterations=config.iterations, pixels_per_step=config.pixels_per_step,
                           scale_jitter=config.scale_jitter, seed=config.seed, device=config.device,
                           checkpoint_every=max(50, config.iterations // 4))
    paths = {"scene": str(data.scene_dir.resolve()), "gaussians": str(data.gaussians.resolve()),
             "bank": str(data.bank_dir.resolve())}
    saved = saved_configs(run_dir) if (run_dir / CHECKPOINT_NAME).is_file() else None
    inputs_ok = saved is not None and _same_inputs(run_dir, paths)
    same = inputs_ok and saved == (field_config, train_config)
    # An interrupted run (or an interrupted extension of a shorter one) has a checkpoint with
    # these settings but a field and report of fewer steps: only a finished run is reused.
    report = json.loads((run_dir / REPORT_NAME).read_text()) \
        if same and (run_dir / FIELD_NAME).is_file() and (run_dir / REPORT_NAME).is_file() else None
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
    extend = inputs_ok and not same and saved[0] == field_config and \
        replace(saved[1], **ignore) == replace(train_config, **ignore) and \
        _checkpoint_step(run_dir) <= train_config.iterations
    resume = same or extend
    if not resume:
        for stale in (CHECKPOINT_NAME, FIELD_NAME, REPORT_NAME, MEMORY_NAME):
            (run_dir / stale).unlink(missing_ok=True)
    log(f"[bench] {run_dir.name}: training {spec.variant} ({spec.backbone}), D={field_config.dim}, "
        f"k={field_config.step_size}, {train_config.iterations} steps"
        + (" (resumed)" if same else " (continuing a shorter run)" if extend else ""))
    scene = load_scene(data.scene_dir)
    bank = SegmentBank.open(data.bank_dir)
    gaussians = read_ply(data.gaussians)
    meter = ActivationMeter()
    with meter:
        report = train_field(scene, gaussians, bank, run_dir, field_config=field_config, config=train_config,
                             resume=resume, paths=paths, progress=config.progress, callback=meter.end_step)
    params = field_parameter_count(field_config, int(bank.embed_dim))
    F_dim = _rasterized_channels(field_config)
    memory = {"parameters": params, "parameter_mb": params * 4 / 2**20,
              # Adam keeps two moments per parameter, and the gradient is one more copy.
              "parameter_adam_grad_mb": 4 * params * 4 / 2**20,
              "activation_peak_mb": meter.peak_bytes / 2**20 if meter.steps else None,
              "activation_median_mb": float(np.median(meter.steps)) / 2**20 if meter.steps else None,
              "rasterized_channels": F_dim, "measured_steps": len(meter.steps)}
    write_json(run_dir / MEMORY_NAME, memory)
    report["memory"] = memory
    report["reused"] = False
    return report


def _rasterized_channels(field_config: Any) -> int:
    """Channels deferred rendering rasterizes: the backbone's output (TriPlane channels, or the
    positional encoding's 3 + 6 L)."""
    if field_config.backbone == "triplane":
        return int(field_config.plane_channels)
    return 3 + 6 * int(field_config.pe_frequencies)


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
        return meta.get("scene") == paths["scene"] and meta.get("bank") == paths["bank"] and \
            meta.get("gaussians") == paths["gaussians"]
    recorded = json.loads(report.read_text()).get("paths", {})
    # The trainer records the copy of the PLY inside the run; the scene and bank are compared.
    return recorded.get("scene") == paths["scene"] and recorded.get("bank") == paths["bank"]


# ------------------------------------------------------------------------------ evaluation
def evaluate_variant(run_dir: Path, data: BenchData, modes: Sequence[str], out_dir: Path,
                     config: BenchConfig, temperature: float = 1.0,
                     log: Callable[[str], None] = print, encoder: Any = None) -> dict:
    """``evaluate_run`` of one run (both box sizes), written to ``out_dir`` (eval.json, eval.md,
    plots); reused when its eval.json is newer than the field and has the same modes and T."""
    from ..io import write_json, write_text
    from ..query.engine import QueryConfig
    from .runner import EvalConfig, evaluate_run, load_eval, markdown_report

    eval_json = out_dir / "eval.json"
    field_pt = run_dir / "field.pt"
    if eval_json.is_file() and eval_json.stat().st_mtime >= field_pt.stat().st_mtime:
        old = load_eval(eval_json)
        if old.get("modes") == list(modes) and old.get("bench_temperature") == temperature:
            log(f"[bench] {run_dir.name}: evaluation {out_dir.name} up to date, reused")
            return old
    log(f"[bench] {run_dir.name}: evaluating {', '.join(modes)} (T = {temperature:g})")
    result = evaluate_run(run_dir, data.label_dir, scene=data.scene_dir, bank=data.bank_dir,
                          config=EvalConfig(modes=tuple(modes), progress=config.progress),
                          query_config=QueryConfig(temperature=temperature), device=config.device,
                          encoder=encoder)
    result.notes.append(f"bench: composite temperature T = {temperature:g}")
    # eval.md and eval.json as `n2f2 eval` writes them (its per-run plots are left out: the bench
    # draws its own); the JSON round trip gives the same dict a reused evaluation has.
    d = result.to_dict()
    d["bench_temperature"] = temperature
    write_text(out_dir / "eval.md", markdown_report(d))
    write_json(eval_json, d)
    return load_eval(eval_json)


def cosine_variant(run_dir: Path, data: BenchData, config: BenchConfig) -> dict:
    """Per-level cosine to the teacher on the run's held-out views (cached in eval_field.json)."""
    from ..data import load_scene
    from ..field import load_field
    from ..gaussians import read_ply
    from ..io import write_json
    from ..segments.bank import SegmentBank
    from ..train.evaluate import evaluate_cosine_by_level

    path = run_dir / "eval_field.json"
    if path.is_file() and path.stat().st_mtime >= (run_dir / "field.pt").stat().st_mtime:
        return json.loads(path.read_text())
    field, meta = load_field(run_dir / "field.pt", device=config.device)
    views = meta.get("heldout_views") or list(range(len(meta.get("train_views", []))))
    result = evaluate_cosine_by_level(field, read_ply(run_dir / "gaussians.ply"), load_scene(data.scene_dir),
                                      SegmentBank.open(data.bank_dir), views, device=config.device)
    write_json(path, result)
    return result


def gamma_statistics(engine: Any, temperature: float) -> dict:
    """Statistics over the Gaussians of ``gamma^3D`` (paper Eq. 6) at ``temperature``: how far it
    is from uniform (max gamma x number of scales; 1 = uniform), its effective number of scales
    ``exp(entropy)``, where its mass sits (mean weight-averaged prefix length / D), and the
    prefix weights ``revcumsum(gamma)`` (paper Eq. 7) at a few dimensions."""
    import torch

    from ..query.composite import composite_weights, prefix_weights

    with torch.no_grad():
        canon = engine.encode(engine.config.canonical)
        gamma = composite_weights(engine.theta, engine.W, canon, engine.step, temperature)  # [N, S]
        N, S = gamma.shape
        mx = gamma.amax(dim=1)
        ent = -(gamma * torch.log(gamma.clamp(min=1e-30))).sum(dim=1)
        dims = torch.tensor(engine.scale_dims, dtype=gamma.dtype)
        centre = (gamma * dims).sum(dim=1) / engine.dim
        ramp = prefix_weights(gamma, engine.dim, engine.step).mean(dim=0)  # [D]
        at = sorted({0, engine.dim // 4, engine.dim // 2, (3 * engine.dim) // 4, engine.dim - 1})
        argmax = gamma.argmax(dim=1)
    q = lambda t, p: float(torch.quantile(t.double(), p))  # noqa: E731
    return {"temperature": temperature, "scales": S, "gaussians": N, "uniform": 1.0 / S,
            "max_gamma_mean": float(mx.mean()), "max_gamma_median": q(mx, 0.5), "max_gamma_p95": q(mx, 0.95),
            "max_gamma_max": float(mx.max()), "max_gamma_x_scales_mean": float(mx.mean()) * S,
            "effective_scales_mean": float(torch.exp(ent).mean()),
            "mass_centre_mean": float(centre.mean()),
            "argmax_first_scale": float((argmax == 0).double().mean()),
            "argmax_last_scale": float((argmax == S - 1).double().mean()),
            "prefix_weight_at": {str(j + 1): float(ramp[j]) for j in at}}


# ------------------------------------------------------------------------------ timing
def timing_breakdown(nested_run: Path, levels_run: Optional[Path], data: BenchData, config: BenchConfig,
                     encoder: Any = None) -> dict:
    """Paper Table 4 on one labelled view: render-and-cache time, time per query at 1 and at 10
    queries, and totals, for composite and explicit (N2F2 field) and levels (3-level field).

    Times are the engine's own (``ViewCache.seconds``, ``QueryResult.seconds``), medians over
    ``timing_repeats``; text embeddings are computed once beforehand (the encoder costs the same
    in every mode) and ``Theta~`` (gamma^3D premultiplied, once per field) is timed separately."""
    import torch

    from ..data import load_scene
    from ..query.engine import QueryEngine

    threads = torch.get_num_threads()
    if config.timing_threads > 0:
        torch.set_num_threads(config.timing_threads)
    try:
        scene = load_scene(data.scene_dir)
        queries = _scene_queries(data.scene_dir)[:10]
        labelled = json.loads((data.scene_dir / "scene.json").read_text()).get("labelled_views") or [0]
        view = int(labelled[0])
        rows, once = [], {}

        def measure(engine: Any, mode: str, label: str) -> None:
            engine.encode(queries + list(engine.config.negatives) + list(engine.config.canonical))
            render, cache = [], []
            for _ in range(config.timing_repeats):
                vc = engine.render_view(view, modes=[mode], rgb=False)
                render.append(vc.seconds["render"])
                cache.append(vc.seconds["cache"])
            per = {}
            for n in (1, len(queries)):
                engine.query(vc, queries[:n], mode)  # warm-up
                per[n] = float(np.median([engine.query(vc, queries[:n], mode).seconds
                                          for _ in range(config.timing_repeats)]))
            r, c = float(np.median(render)), float(np.median(cache))
            n = len(queries)
            rows.append({"method": label, "mode": mode, "scales": _num_scales(engine, mode),
                         "render_s": r, "cache_s": c, "query_1_s": per[1], "per_query_s": per[n] / n,
                         f"queries_{n}_s": per[n], "total_1_s": r + c + per[1], f"total_{n}_s": r + c + per[n],
                         "num_queries": n})

        engine = QueryEngine.from_run(nested_run, device=config.device, scene=scene, encoder=encoder)
        t0 = time.perf_counter()
        _ = engine.theta_tilde
        once["theta_tilde_s"] = time.perf_counter() - t0
        once["gaussians"] = int(engine.gaussians.means.shape[0])
        measure(engine, "composite", "N2F2 composite")
        measure(engine, "explicit", f"N2F2 explicit ({len(engine.scale_dims)} scales, LERF-like)")
        if levels_run is not None:
            lv = QueryEngine.from_run(levels_run, device=config.device, scene=scene, encoder=encoder)
            measure(lv, "levels", "3-level field (LangSplat-like)")
        cam = scene.cameras[view]
        return {"rows": rows, "once": once, "view": view, "size": [cam.width, cam.height], "dim": engine.dim,
                "threads": torch.get_num_threads(), "repeats": config.timing_repeats, "queries": queries}
    finally:
        torch.set_num_threads(threads)


def _num_scales(engine: Any, mode: str) -> int:
    if mode == "composite":
        return 1
    if mode == "levels":
        return 3
    return len(engine.scale_dims)


def _scene_queries(scene_dir: Path) -> list[str]:
    path = scene_dir / "queries.json"
    if not path.is_file():
        raise InputError(path, "the demo scene has no queries.json")
    return [q["query"] for q in json.loads(path.read_text())["queries"]]


# ------------------------------------------------------------------------------ the bench
def run_bench(out: Union[str, Path], config: Optional[BenchConfig] = None, *,
              scene: Optional[Union[str, Path]] = None, gaussians: Optional[Union[str, Path]] = None,
              bank: Optional[Union[str, Path]] = None, log: Callable[[str], None] = print) -> dict:
    """Run every requested variant (see the module docstring); writes ``OUT/bench.json``,
    ``OUT/bench.md`` and ``OUT/*.png`` and returns the bench.json content."""
    from ..io import write_json, write_text

    config = config or BenchConfig()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    load_start = os.getloadavg()
    stage_s: dict[str, float] = {}

    data = prepare_data(out, config, scene=scene, gaussians=gaussians, bank=bank, log=log)
    stage_s.update({f"data: {k}": v for k, v in data.seconds.items()})
    from ..segments.bank import SegmentBank
    from ..segments.encoders import get_encoder

    # One text encoder for every evaluation (each engine would load its own and re-encode).
    encoder = MemoEncoder(get_encoder(SegmentBank.open(data.bank_dir).encoder_spec, device=config.device))

    specs = [VARIANTS[v] for v in config.variants]
    runs: dict[str, dict] = {}  # run name -> {"train", "evals", "cosine"}
    variant_runs: dict[str, str] = {}
    for spec in specs:
        name = run_name(spec, config.dim)
        variant_runs[spec.name] = name
        run_dir = out / "runs" / name
        entry = runs.setdefault(name, {"evals": {}, "cosine": None, "modes": [], "cosine_wanted": False,
                                       "variant": spec.variant, "backbone": spec.backbone})
        entry["modes"] = list(dict.fromkeys(entry["modes"] + list(spec.modes)))
        entry["cosine_wanted"] |= spec.cosine
        if "train" not in entry:
            t0 = time.perf_counter()
            entry["train"] = train_variant(spec, data, run_dir, config, log)
            stage_s[f"train {name}"] = time.perf_counter() - t0
    for name, entry in runs.items():
        run_dir = out / "runs" / name
        t0 = time.perf_counter()
        modes = _mode_order(entry["modes"])
        entry["evals"]["T1"] = evaluate_variant(run_dir, data, modes, run_dir / "eval", config, 1.0, log, encoder)
        if entry["cosine_wanted"]:
            entry["cosine"] = cosine_variant(run_dir, data, config)
        stage_s[f"eval {name}"] = time.perf_counter() - t0

    # Composite temperature on the k = 1 nested TriPlane run.
    gamma: list[dict] = []
    main_name = variant_runs.get("nested")
    if main_name is not None:
        from ..query.engine import QueryConfig, QueryEngine

        t0 = time.perf_counter()
        main_dir = out / "runs" / main_name
        for T in config.temperatures:
            engine = QueryEngine.from_run(main_dir, device=config.device, scene=data.scene_dir,
                                          config=QueryConfig(temperature=T), encoder=encoder)
            gamma.append(gamma_statistics(engine, T))
            if T != 1.0:
                runs[main_name]["evals"][_tag(T)] = evaluate_variant(
                    main_dir, data, ["composite"], main_dir / f"eval_{_tag(T)}", config, T, log, encoder)
        stage_s["temperature"] = time.perf_counter() - t0

    paper_params = None
    if "mlp" in variant_runs and main_name is not None:
        from ..field import FieldConfig

        E = int(encoder_dim(data))
        paper_params = {b: field_parameter_count(FieldConfig.paper(backbone=b), E) for b in ("triplane", "mlp")}

    timing = None
    if main_name is not None:
        t0 = time.perf_counter()
        log("[bench] timing breakdown (Table 4)")
        levels_dir = out / "runs" / variant_runs["levels"] if "levels" in variant_runs else None
        timing = timing_breakdown(out / "runs" / main_name, levels_dir, data, config, encoder)
        stage_s["timing"] = time.perf_counter() - t0

    result = {
        "format": "n2f2-bench-v1",
        "config": asdict(config),
        "data": {"scene": str(data.scene_dir), "gaussians": str(data.gaussians), "bank": str(data.bank_dir),
                 "labels": str(data.label_dir), "built": data.built,
                 # what the bank was built with (a given --bank need not match config.scale_measure)
                 "scale_measure": json.loads((data.bank_dir / "bank.json").read_text())["lifting"].get(
                     "scale_measure", "eigenvalue")},
        "environment": _environment(),
        "variant_runs": variant_runs,
        "steps": {name: scaled_step(VARIANTS[v].paper_step, config.dim) for v, name in variant_runs.items()
                  if VARIANTS[v].variant == "nested"},
        "runs": {name: _run_summary(entry) for name, entry in runs.items()},
        "gamma": gamma,
        "timing": timing,
        "paper_size_parameters": paper_params,
        "stage_seconds": stage_s,
        "load_average": {"start": list(load_start), "end": list(os.getloadavg())},
    }
    result["claims"] = evaluate_claims(result, runs, variant_runs)
    result["seconds"] = time.perf_counter() - t_start
    plots = write_plots(out, result, runs, variant_runs)
    result["plots"] = {k: str(v) for k, v in plots.items()}
    write_text(out / "bench.md", markdown_bench(result, runs, variant_runs))
    write_json(out / "bench.json", {**result, "evals": {n: e["evals"] for n, e in runs.items()}})
    log(f"[bench] done in {result['seconds']:.0f} s -> {out / 'bench.md'}")
    return result


def encoder_dim(data: BenchData) -> int:
    """E, the teacher embedding size of the bank."""
    from ..segments.bank import SegmentBank

    return int(SegmentBank.open(data.bank_dir).embed_dim)


def _tag(T: float) -> str:
    return f"T{T:g}"


def _mode_order(modes: Sequence[str]) -> list[str]:
    from ..query.engine import MODES

    return [m for m in MODES if m in modes]


def _environment() -> dict:
    import platform

    import torch

    return {"torch": torch.__version__, "threads": torch.get_num_threads(), "cpus": os.cpu_count(),
            "python": platform.python_version(), "machine": platform.machine()}


def _run_summary(entry: Mapping) -> dict:
    t = entry["train"]
    return {"variant": entry["variant"], "backbone": entry["backbone"],
            "field_config": t.get("field_config"), "steps": t.get("steps"), "final_loss": t.get("final_loss"),
            "train_time_s": t.get("train_time_s"), "time_per_iteration_s": t.get("time_per_iteration_s"),
            "cpu_time_per_iteration_s": t.get("cpu_time_per_iteration_s"), "reused": t.get("reused"),
            "num_gaussians": t.get("num_gaussians"), "memory": t.get("memory"), "curve": t.get("curve"),
            "cosine": entry.get("cosine"), "evals": sorted(entry["evals"])}


# ------------------------------------------------------------------------------ claims
def _score(ev: Mapping, mode: str, box: str, key: str = "miou") -> float:
    return float(ev["scores"][mode][box][key])


def paired_difference(ev_a: Mapping, mode_a: str, ev_b: Mapping, mode_b: str, box: str,
                      key: str = "iou") -> dict:
    """Mean of ``a - b`` over the (frame, query) pairs both scored, and its standard error
    (``key`` = "iou" for segmentation, "hit" for localization)."""
    pa = {(p["frame"], p["category"]): float(p[key]) for p in ev_a["scores"][mode_a][box]["pairs"]}
    pb = {(p["frame"], p["category"]): float(p[key]) for p in ev_b["scores"][mode_b][box]["pairs"]}
    shared = sorted(set(pa) & set(pb))
    d = np.array([pa[k] - pb[k] for k in shared], dtype=np.float64)
    if d.size == 0:
        return {"delta": math.nan, "se": math.nan, "pairs": 0}
    se = float(d.std(ddof=1) / math.sqrt(d.size)) if d.size > 1 else math.nan
    return {"delta": float(d.mean()), "se": se, "pairs": int(d.size)}


def _verdict(delta: float, se: float, expect_positive: bool = True) -> str:
    """"holds" / "does not hold", with "(within noise)" when |delta| < 2 standard errors."""
    if not np.isfinite(delta):
        return "n/a"
    ok = delta >= 0 if expect_positive else delta <= 0
    noise = np.isfinite(se) and abs(delta) < 2 * se
    return ("holds" if ok else "does not hold") + (" (within noise)" if noise and delta != 0 else "")


def evaluate_claims(result: Mapping, runs: Mapping[str, dict], variant_runs: Mapping[str, str]) -> list[dict]:
    """Each claim of the paper the bench can test (per box and metric where it is a score), with
    the number measured here (``here``, in points for scores) and a verdict."""
    claims: list[dict] = []

    def ev(variant: str, tag: str = "T1") -> Optional[Mapping]:
        name = variant_runs.get(variant)
        return runs[name]["evals"].get(tag) if name else None

    def add(claim: str, paper: str, box: str, metric: str, delta: float, se: float, pairs: Optional[int],
            verdict: str, here: Optional[str] = None, **extra: Any) -> None:
        claims.append({"claim": claim, "paper": paper, "box": box, "metric": metric, "delta": delta, "se": se,
                       "pairs": pairs, "here": here if here is not None else _signed_pts(delta, se) + " pts",
                       "verdict": verdict, **extra})

    def compare(claim: str, paper: str, a: Optional[Mapping], ma: str, b: Optional[Mapping], mb: str,
                similar: Optional[tuple[str, str]] = None) -> None:
        if a is None or b is None or ma not in a["scores"] or mb not in b["scores"] or (a is b and ma == mb):
            return  # not run, or the same run (two paper settings that map to one k at this D)
        for box in BOXES:
            for metric, key in (("mIoU", "iou"), ("loc.", "hit")):
                d = paired_difference(a, ma, b, mb, box, key)
                verdict = _similar(d["delta"], d["se"], similar) if similar else _verdict(d["delta"], d["se"])
                add(claim, paper, box, metric, d["delta"], d["se"], d["pairs"], verdict)

    nested = ev("nested")
    compare("composite >= explicit (Table 3)", "+0.7 mIoU, +0.9 loc.", nested, "composite", nested, "explicit")
    compare("oracle >= composite (oracle = upper bound, Table 3)", "+2.9 mIoU, +2.7 loc.", nested, "oracle",
            nested, "composite")
    compare("oracle >= explicit (by construction)", "+3.6 mIoU, +3.6 loc.", nested, "oracle", nested, "explicit")
    compare("N2F2 explicit (D scales) >= 3-level LangSplat-like (Sec. 4.3)", "explicit beats LangSplat",
            nested, "explicit", ev("levels"), "levels")
    compare("N2F2 composite >= 3-level LangSplat-like", "+ (Tables 1, 2)", nested, "composite", ev("levels"), "levels")
    compare("nested >= non-nested (appendix)", "+2.0 mIoU, +2.5 loc.", nested, "composite", ev("flat"), "composite")
    for k in PAPER_STEPS[1:]:
        compare(f"k=1 >= k={k} (Table 6)", "k=1 best, monotone", nested, "composite", ev(f"k{k}"), "composite")
    compare("TriPlane+MLP ~ PE+MLP accuracy (appendix)", "similar final performance", nested, "composite",
            ev("mlp"), "composite", similar=("TriPlane+MLP", "PE+MLP"))
    for T in result["config"]["temperatures"]:
        if T != 1.0:
            compare(f"composite T=1 (paper) >= T={T:g}", "T=1 is the paper's", nested, "composite",
                    ev("nested", _tag(T)), "composite")
    lv = ev("levels")
    if nested is not None and lv is not None:
        for box in BOXES:
            g = compound_gain(nested, "composite", lv, "levels", box)
            add("compound queries gain most over the 3-level field (Table 7)", "gain on compound > on simple",
                box, "mIoU", g["delta"], g["se"], g["pairs"], _verdict(g["delta"], g["se"]),
                here=f"{_signed_pts(g['delta'], g['se'])} pts (compound {_signed_pts(g['compound'])}, "
                     f"simple {_signed_pts(g['simple'])})")
    _efficiency_claims(result, variant_runs, add)
    return claims


def compound_gain(ev_a: Mapping, mode_a: str, ev_b: Mapping, mode_b: str, box: str) -> dict:
    """(a - b) on compound queries minus (a - b) on simple queries, over the pairs both scored, with
    the standard error of that difference of two independent means."""
    types = ev_a.get("query_types", {})
    pa = {(p["frame"], p["category"]): p["iou"] for p in ev_a["scores"][mode_a][box]["pairs"]}
    pb = {(p["frame"], p["category"]): p["iou"] for p in ev_b["scores"][mode_b][box]["pairs"]}
    diffs = {k: np.array([pa[q] - pb[q] for q in sorted(set(pa) & set(pb)) if types.get(q[1]) == k], np.float64)
             for k in ("simple", "compound")}
    if any(d.size < 2 for d in diffs.values()):
        return {"delta": math.nan, "se": math.nan, "pairs": int(sum(d.size for d in diffs.values())),
                "simple": math.nan, "compound": math.nan}
    se = math.sqrt(sum(d.var(ddof=1) / d.size for d in diffs.values()))
    return {"delta": float(diffs["compound"].mean() - diffs["simple"].mean()), "se": se,
            "pairs": int(sum(d.size for d in diffs.values())),
            "simple": float(diffs["simple"].mean()), "compound": float(diffs["compound"].mean())}


def _similar(delta: float, se: float, names: tuple[str, str], tolerance: float = 0.02) -> str:
    """Verdict of a "similar" claim (``delta`` = first - second): within noise (2 SE) or within
    ``tolerance`` (2 points)."""
    if not np.isfinite(delta):
        return "n/a"
    if abs(delta) <= tolerance or (np.isfinite(se) and abs(delta) < 2 * se):
        return "holds (similar)"
    return f"does not hold ({names[0] if delta > 0 else names[1]} better)"


def _efficiency_claims(result: Mapping, variant_runs: Mapping[str, str], add: Callable[..., None]) -> None:
    """Convergence and memory of the two backbones, and query speed (ratios, not paired scores)."""
    runs = result["runs"]
    if "nested" in variant_runs and "mlp" in variant_runs:
        tri, mlp = runs[variant_runs["nested"]], runs[variant_runs["mlp"]]
        conv = convergence({"tri": tri["curve"], "mlp": mlp["curve"]})
        if conv.get("tri") and conv.get("mlp"):
            ratio = conv["mlp"] / conv["tri"]
            add("TriPlane+MLP converges faster than PE+MLP (appendix)", "20x fewer steps", "-", "steps", ratio,
                math.nan, None, "holds" if ratio > 1 else "does not hold",
                here=f"{ratio:.1f}x (steps to loss {conv['target_loss']:.5f}: {conv['tri']} vs {conv['mlp']})")
        mt, mm = tri.get("memory") or {}, mlp.get("memory") or {}
        if mt.get("activation_peak_mb") and mm.get("activation_peak_mb"):
            total_t = mt["parameter_adam_grad_mb"] + mt["activation_peak_mb"]
            total_m = mm["parameter_adam_grad_mb"] + mm["activation_peak_mb"]
            paper = result.get("paper_size_parameters") or {}
            at_paper = (f"; parameters at paper size {paper['triplane'] / max(paper['mlp'], 1):.0f}x"
                        if paper.get("triplane") and paper.get("mlp") else "")
            add("PE+MLP needs less training memory than TriPlane+MLP (appendix)", "2.3x less", "-", "MB",
                total_t / total_m, math.nan, None, "holds" if total_m < total_t else "does not hold",
                here=f"{total_t / total_m:.1f}x (params+grad+Adam+activations {total_t:.0f} vs {total_m:.0f} MB"
                     f"{at_paper})")
    tm = result.get("timing")
    if tm:
        rows = {r["mode"]: r for r in tm["rows"]}
        n = tm["rows"][0]["num_queries"]
        comp = rows.get("composite")
        if comp and "explicit" in rows:
            ratio = rows["explicit"]["per_query_s"] / comp["per_query_s"]
            add("composite queries faster than explicit scale selection (Sec. 4.3)", "~5x", "-", "time", ratio,
                math.nan, None, "holds" if ratio > 1 else "does not hold",
                here=f"{ratio:.0f}x per query (at {n} queries)")
        if comp and "levels" in rows:
            ratio = rows["levels"][f"total_{n}_s"] / comp[f"total_{n}_s"]
            add(f"N2F2 total time for {n} queries < 3-level field's (Table 4)", "1.7x faster", "-", "time", ratio,
                math.nan, None, "holds" if ratio > 1 else "does not hold",
                here=f"{ratio:.1f}x (render + {n} queries)")


# ------------------------------------------------------------------------------ backbone
def convergence(curves: Mapping[str, Mapping]) -> dict:
    """Steps to reach the higher of the runs' final losses (a level every run reaches), per run,
    on the trainer's logged loss curve (means over ``log_every`` steps)."""
    finals = {n: c["loss"][-1] for n, c in curves.items() if c and c.get("loss")}
    if not finals:
        return {}
    target = max(finals.values())
    out = {"target_loss": target}
    for n, c in curves.items():
        steps = [s for s, l in zip(c["step"], c["loss"]) if l <= target]
        out[n] = steps[0] if steps else None
    return out


# ------------------------------------------------------------------------------ plots
def _line_plot(path: Path, curves: Mapping[str, tuple], xlabel: str, ylabel: str, title: str,
               logy: bool = False) -> Path:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from ..io import atomic_path

    fig = Figure(figsize=(5.0, 3.4))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    for name, (x, y) in curves.items():
        ax.plot(x, y, label=name, marker="o" if len(x) < 12 else None)
    if logy:
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120, bbox_inches="tight")
    return path


def write_plots(out: Path, result: Mapping, runs: Mapping[str, dict], variant_runs: Mapping[str, str]) -> dict:
    """mIoU per method (both boxes), the k sweep, and the training loss curves."""
    from .reports import plot_grouped_bars

    plots: dict[str, Path] = {}
    methods = _method_rows(runs, variant_runs)
    if methods:
        values = {f"mIoU ({b})": {label: _score(e, m, b) for label, e, m in methods} for b in BOXES}
        values.update({f"loc. ({b})": {label: _score(e, m, b, "loc_accuracy") for label, e, m in methods}
                       for b in BOXES})
        plots["methods"] = plot_grouped_bars(out / "methods.png", values, title="demo scene: per method")
    ks = _k_rows(runs, variant_runs, result)
    if len(ks) > 1:
        curves = {}
        for mode in ("composite", "explicit", "oracle"):
            for b in BOXES:
                pts = [(k, _score(e, mode, b)) for k, _, e in ks if mode in e["scores"]]
                if pts:
                    curves[f"{mode} ({b})"] = ([p[0] for p in pts], [100 * p[1] for p in pts])
        plots["k_sweep"] = _line_plot(out / "k_sweep.png", curves, "paper step size k (log scale of scales)",
                                      "mIoU %", "step size k (Table 6)")
    curves = {name: (r["curve"]["step"], r["curve"]["loss"]) for name, r in result["runs"].items()
              if r.get("curve") and r["curve"].get("loss")}
    if curves:
        plots["loss"] = _line_plot(out / "loss_curves.png", curves, "step", "training loss (L2 + 0.001 cos)",
                                   "training loss", logy=True)
    return plots


def _method_rows(runs: Mapping[str, dict], variant_runs: Mapping[str, str]) -> list[tuple[str, Mapping, str]]:
    rows = []
    wanted = [("nested", "composite", "N2F2 composite"), ("nested", "explicit", "N2F2 explicit"),
              ("nested", "oracle", "N2F2 oracle"), ("flat", "composite", "flat composite"),
              ("levels", "levels", "3-level"), ("levels", "oracle", "3-level oracle"),
              ("mlp", "composite", "MLP-backbone composite")]
    for variant, mode, label in wanted:
        name = variant_runs.get(variant)
        if name and mode in runs[name]["evals"]["T1"]["scores"]:
            rows.append((label, runs[name]["evals"]["T1"], mode))
    return rows


def _k_rows(runs: Mapping[str, dict], variant_runs: Mapping[str, str], result: Mapping) -> list[tuple[int, str, Mapping]]:
    rows = []
    for k in PAPER_STEPS:
        v = "nested" if k == 1 else f"k{k}"
        name = variant_runs.get(v)
        if name:
            rows.append((k, name, runs[name]["evals"]["T1"]))
    return rows


# ------------------------------------------------------------------------------ report
def _pct(v: Any) -> str:
    from .reports import _fmt

    return _fmt(v, percent=True)


def _signed_pts(d: float, se: float = math.nan) -> str:
    if d is None or not np.isfinite(d):
        return "n/a"
    s = f"{100 * d:+.1f}"
    return s + (f" ± {100 * se:.1f}" if np.isfinite(se) else "")


def _box_title(ev: Mapping, box: str) -> str:
    return f"{box} {','.join(str(s) for s in ev['boxes'][box]['box_sizes'])} px"


def markdown_bench(result: Mapping, runs: Mapping[str, dict], variant_runs: Mapping[str, str]) -> str:
    """``bench.md`` from the collected results."""
    from .reports import markdown_table

    cfg = result["config"]
    any_ev = next(iter(next(iter(runs.values()))["evals"].values()))
    bt = {b: _box_title(any_ev, b) for b in BOXES}
    first = next(iter(result["runs"].values()))
    out: list[str] = ["# n2f2 bench: the paper's ablations on the demo scene\n\n"]
    steps = result["steps"]
    k_map = ", ".join(f"k={VARIANTS[v].paper_step} -> {steps[n]}" for v, n in variant_runs.items()
                      if VARIANTS[v].variant == "nested" and VARIANTS[v].backbone == "triplane")
    out.append(
        f"- scene: `{result['data']['scene']}` ({any_ev['scene']}), Gaussians `{result['data']['gaussians']}` "
        f"({first['num_gaussians']} Gaussians), segment bank `{result['data']['bank']}`; "
        f"built now: {', '.join(k for k, v in result['data']['built'].items() if v) or 'nothing (all reused)'}\n"
        f"- teacher / text encoder: {any_ev['encoder']['description']}\n"
        f"- every field: D = {cfg['dim']}, TriPlane {first['field_config']['plane_resolution']}^2 x "
        f"{first['field_config']['plane_channels']}, MLP hidden {first['field_config']['hidden']}, "
        f"{cfg['iterations']} steps of {cfg['pixels_per_step']} pixels, seed {cfg['seed']}, one seed per variant\n"
        f"- segment scales: {result['data'].get('scale_measure', 'eigenvalue')} measure, training scale jitter "
        f"{cfg.get('scale_jitter', 0.0)} (paper: eigenvalue, 0)\n"
        f"- step sizes (paper D = 512 -> this D = {cfg['dim']}, keeping floor(512 / k) scales): {k_map or 'n/a'}\n"
        f"- protocol: LangSplat's, always both boxes: **{bt['exact']}** (LangSplat's, sized for ~986 px-wide "
        f"images) and **{bt['scaled']}** (scaled to the image width). On the small demo renders the 30 px box "
        f"erases small parts.\n"
        f"- {any_ev['scores'][any_ev['modes'][0]]['exact']['num_pairs']} (frame, query) pairs on "
        f"{any_ev['scores'][any_ev['modes'][0]]['exact']['num_frames']} labelled frames. Deltas are paired over "
        f"these pairs, shown as mean ± standard error in points; \"within noise\" = |delta| < 2 SE.\n"
        f"- machine: {result['environment']['cpus']} CPUs, torch {result['environment']['torch']} "
        f"({result['environment']['threads']} threads); load average at start "
        f"{result['load_average']['start'][0]:.1f}, at end {result['load_average']['end'][0]:.1f}; "
        f"bench wall time {result['seconds'] / 60:.1f} min\n")
    for note in any_ev.get("notes", []):
        if "Teacher" in note:
            out.append(f"- note: {note}\n")

    # Claims.
    out.append("\n## Verdicts: which of the paper's claims hold here\n\n")
    rows = [[c["claim"], c["paper"], c["box"], c["metric"], c["here"], c["verdict"]] for c in result["claims"]]
    out.append(markdown_table(["claim", "paper", "box", "metric", "here", "verdict"], rows,
                              ["l", "l", "l", "l", "r", "l"]))

    # Table 3.
    nested = runs[variant_runs["nested"]]["evals"]["T1"] if "nested" in variant_runs else None
    if nested is not None:
        out.append("\n## Composite vs explicit vs oracle (paper Table 3)\n\n")
        out.append(f"N2F2 field ({variant_runs['nested']}), {nested['field']['num_scales']} scales.\n\n")
        out.append(_mode_table([("composite", nested, "composite"), ("explicit", nested, "explicit"),
                                ("oracle (upper bound of explicit)", nested, "oracle")], bt))
        out.append("\nScales chosen per (frame, query) pair (prefix length d of the chosen scale, D = "
                   f"{nested['field']['dim']}):\n\n")
        out.append(_choice_table(nested, ["explicit", "oracle"]))

    # 3-level baseline.
    if "levels" in variant_runs:
        lv = runs[variant_runs["levels"]]["evals"]["T1"]
        out.append("\n## N2F2 vs the 3-level LangSplat-like field (same data)\n\n")
        out.append("The 3-level field splits theta into 3 blocks, each supervised by one tercile of the "
                   "quantized scale, and answers a query with LangSplat's level choice.\n\n")
        rows = [("3-level (levels mode)", lv, "levels"), ("3-level oracle", lv, "oracle")]
        if nested is not None:
            rows = [("N2F2 composite", nested, "composite"), ("N2F2 explicit", nested, "explicit")] + rows
        out.append(_mode_table(rows, bt))
        out.append("\n### Simple vs compound queries (paper Table 7)\n\n")
        out.append(_split_table(rows, bt))
        if nested is not None:
            out.append("\n### Per-query IoU delta, N2F2 composite - 3-level (paper Table 8: top and bottom 3)\n\n")
            out.append(_delta_tables(lv, "levels", nested, "composite", bt))

    # Nested vs flat.
    if "flat" in variant_runs or "nested" in variant_runs:
        out.append("\n## Nested vs non-nested\n\n")
        rows = []
        if nested is not None:
            rows.append(("nested composite", nested, "composite"))
        if "flat" in variant_runs:
            rows.append(("flat composite (= explicit = oracle: 1 scale)",
                         runs[variant_runs["flat"]]["evals"]["T1"], "composite"))
        out.append(_mode_table(rows, bt))
        out.append("\nMean cosine between phi(u, s) and the teacher embedding of the ground-truth segment "
                   "covering u, on held-out views (`evaluate_cosine_by_level`; each variant's own mask B(s)):\n\n")
        out.append(_cosine_table(result, variant_runs))

    # k sweep.
    ks = _k_rows(runs, variant_runs, result)
    if len(ks) > 1:
        out.append("\n## Step size k (paper Table 6: 69.2, 68.7, 68.1, 67.2, 66.4 mIoU on teatime)\n\n")
        rows = []
        for k, name, e in ks:
            rows.append([k, steps.get(name, "-"), e["field"]["num_scales"]]
                        + [_pct(_score(e, m, b)) for m in ("composite", "explicit", "oracle") for b in BOXES]
                        + [_pct(_score(e, "composite", b, "loc_accuracy")) for b in BOXES])
        out.append(markdown_table(["paper k", "k here", "scales"]
                                  + [f"{m} mIoU % ({bt[b]})" for m in ("composite", "explicit", "oracle") for b in BOXES]
                                  + [f"composite loc. % ({bt[b]})" for b in BOXES], rows))

    # Temperature.
    if result["gamma"]:
        out.append("\n## Composite temperature T: gamma = softmax(score / T) (T = 1 is the paper)\n\n")
        out.append("max gamma x scales = 1 means uniform weights; effective scales = exp(entropy of gamma); "
                   "mass centre = gamma-weighted prefix length / D; prefix weight r_j = sum_{d >= j} gamma_d "
                   "(paper Eq. 7) averaged over the Gaussians.\n\n")
        g0 = result["gamma"][0]
        at = list(g0["prefix_weight_at"])
        rows = []
        main = runs[variant_runs["nested"]]["evals"]
        for g in result["gamma"]:
            e = main.get(_tag(g["temperature"]) if g["temperature"] != 1.0 else "T1")
            rows.append([f"{g['temperature']:g}", g["scales"], f"{g['max_gamma_mean']:.4g}",
                         f"{g['max_gamma_x_scales_mean']:.2f}", f"{g['max_gamma_p95'] * g['scales']:.2f}",
                         f"{g['effective_scales_mean']:.1f}", f"{g['mass_centre_mean']:.2f}"]
                        + [f"{g['prefix_weight_at'][j]:.2f}" for j in at]
                        + ([_pct(_score(e, "composite", b)) for b in BOXES]
                           + [_pct(_score(e, "composite", b, "loc_accuracy")) for b in BOXES]
                           + [_pct(e["split"]["composite"]["scaled"][k]["miou"]) for k in ("simple", "compound")]
                           if e else ["-"] * 6))
        out.append(markdown_table(["T", "scales", "mean max gamma", "mean max gamma x scales",
                                   "p95 max gamma x scales", "effective scales", "mass centre"]
                                  + [f"r_{j}" for j in at]
                                  + [f"mIoU % ({bt[b]})" for b in BOXES] + [f"loc. % ({bt[b]})" for b in BOXES]
                                  + ["simple mIoU % (scaled)", "compound mIoU % (scaled)"], rows))

    # Backbone.
    if "mlp" in variant_runs and "nested" in variant_runs:
        out.append("\n## TriPlane+MLP vs MLP backbone (appendix: similar accuracy, TriPlane 20x faster "
                   "convergence, MLP 2.3x less memory)\n\n")
        names = {"TriPlane+MLP": variant_runs["nested"], "PE+MLP": variant_runs["mlp"]}
        conv = convergence({n: result["runs"][r]["curve"] for n, r in names.items()})
        rows = []
        for label, name in names.items():
            r = result["runs"][name]
            mem = r.get("memory") or {}
            e = runs[name]["evals"]["T1"]
            rows.append([label, mem.get("parameters", "-"), _mb(mem.get("parameter_adam_grad_mb")),
                         _mb(mem.get("activation_peak_mb")), mem.get("rasterized_channels", "-"),
                         _millions((result.get("paper_size_parameters") or {}).get(r["backbone"])),
                         _ms(r.get("time_per_iteration_s")), _ms(r.get("cpu_time_per_iteration_s")),
                         f"{r['final_loss']:.5f}", conv.get(label, "-") if conv.get(label) is not None else "not reached",
                         _pct(_score(e, "composite", "exact")), _pct(_score(e, "composite", "scaled"))]
                        + _cos_cells(r.get("cosine")))
        cos_names = _cos_names(result)
        out.append(markdown_table(["backbone", "parameters", "params+grad+Adam MB", "activations / step MB",
                                   "rasterized channels", "parameters at paper size", "ms / step (wall)",
                                   "ms / step (CPU)", "final loss",
                                   f"steps to loss {conv.get('target_loss', math.nan):.5f}",
                                   f"composite mIoU % ({bt['exact']})", f"composite mIoU % ({bt['scaled']})"]
                                  + [f"cos {n}" for n in cos_names], rows))
        out.append("\nActivations: bytes autograd saved for backward in one training step (peak over steps; "
                   "parameters excluded). The paper's memory numbers are GPU totals at paper size (TriPlane "
                   "512^2 x 64); the parameter column at paper size shows where that ratio comes from. The "
                   "process RSS on CPU is dominated by torch, the scene and the bank and is not compared.\n")

    # Timing.
    if result["timing"]:
        tm = result["timing"]
        n = tm["rows"][0]["num_queries"]
        out.append(f"\n## Query time breakdown (paper Table 4; one {tm['size'][0]}x{tm['size'][1]} view, "
                   f"D = {tm['dim']}, {tm['threads']} torch thread(s), medians of {tm['repeats']})\n\n")
        rows = [[r["method"], r["scales"], _ms(r["render_s"]), _ms(r["cache_s"]), _ms(r["query_1_s"]),
                 _ms(r["per_query_s"]), _ms(r[f"queries_{n}_s"]), _ms(r["total_1_s"]), _ms(r[f"total_{n}_s"])]
                for r in tm["rows"]]
        out.append(markdown_table(["method", "maps per query", "render ms", "cache ms", "1 query ms",
                                   f"per query ms (at {n})", f"{n} queries ms", "total 1 query ms",
                                   f"total {n} queries ms"], rows))
        out.append(f"\nOnce per field: Theta~ = revcumsum(gamma^3D) * Theta for {tm['once']['gaussians']} "
                   f"Gaussians in {_ms(tm['once']['theta_tilde_s'])} ms. Explicit / levels pick a scale per "
                   "query with LangSplat's smoothed maximum (the protocol's rule). Unlike LangSplat, the "
                   "3-level field renders D channels (no 3-d latent + decoder).\n")

    out.append("\n## Runs\n\n")
    rows = [[name, r["variant"], r["backbone"], r["field_config"]["step_size"], r["steps"],
             f"{r['final_loss']:.5f}", f"{r['train_time_s']:.0f}", "yes" if r["reused"] else "no",
             ", ".join(r["evals"])] for name, r in result["runs"].items()]
    out.append(markdown_table(["run", "variant", "backbone", "k", "steps", "final loss", "train s (this session)",
                               "reused", "evaluations"], rows, ["l", "l", "l", "r", "r", "r", "r", "l", "l"]))
    out.append("\nStage wall times: " + ", ".join(f"{k} {v:.0f} s" for k, v in result["stage_seconds"].items())
               + ".\n\nPlots: " + ", ".join(f"`{Path(p).name}`" for p in result.get("plots", {}).values()) + ".\n")
    return "".join(out)


def _millions(v: Any) -> str:
    return "-" if v is None else f"{v / 1e6:.2f} M"


def _ms(v: Any) -> str:
    if v is None:
        return "-"
    ms = 1000 * float(v)
    return f"{ms:.1f}" if ms >= 10 else f"{ms:.3f}"


def _mb(v: Any) -> str:
    return "-" if v is None else f"{float(v):.1f}"


def _mode_table(rows: Sequence[tuple[str, Mapping, str]], bt: Mapping[str, str]) -> str:
    from .reports import markdown_table

    body = [[label] + [_pct(_score(e, m, b, "loc_accuracy")) for b in BOXES] + [_pct(_score(e, m, b)) for b in BOXES]
            for label, e, m in rows]
    return markdown_table(["method"] + [f"loc. % ({bt[b]})" for b in BOXES] + [f"mIoU % ({bt[b]})" for b in BOXES],
                          body)


def _split_table(rows: Sequence[tuple[str, Mapping, str]], bt: Mapping[str, str]) -> str:
    from .reports import markdown_table

    body = []
    for label, e, m in rows:
        for b in BOXES:
            sp = e["split"][m][b]
            body.append([label, bt[b], _pct(sp["simple"]["miou"]), _pct(sp["compound"]["miou"]),
                         _pct(sp["simple"]["loc_accuracy"]), _pct(sp["compound"]["loc_accuracy"]),
                         sp["simple"]["pairs"], sp["compound"]["pairs"]])
    return markdown_table(["method", "box", "simple mIoU %", "compound mIoU %", "simple loc. %",
                           "compound loc. %", "simple pairs", "compound pairs"], body, ["l", "l"] + ["r"] * 6)


def _delta_tables(ref: Mapping, ref_mode: str, cur: Mapping, cur_mode: str, bt: Mapping[str, str]) -> str:
    from .metrics import query_deltas
    from .reports import markdown_table

    out = []
    for b in BOXES:
        a = {q: v["iou"] for q, v in ref["per_query"][ref_mode][b].items()}
        c = {q: v["iou"] for q, v in cur["per_query"][cur_mode][b].items()}
        d = query_deltas(a, c, n=3)
        types = cur.get("query_types", {})
        rows = [[tag, x.query, types.get(x.query, "unknown"), _pct(x.a), _pct(x.b), _signed_pts(x.delta)]
                for tag, items in (("top", d.top), ("bottom", d.bottom)) for x in items]
        out.append(f"{bt[b]}: mean delta {_signed_pts(d.mean_delta)} points over {len(d.deltas)} queries\n\n")
        out.append(markdown_table(["", "query", "type", "3-level IoU %", "N2F2 IoU %", "delta"], rows,
                                  ["l", "l", "l", "r", "r", "r"]))
        out.append("\n")
    return "".join(out)


def _choice_table(ev: Mapping, modes: Sequence[str]) -> str:
    from .reports import markdown_table

    dims = [int(s.split("=")[1]) for s in ev["field"]["scale_labels"]]
    rows = []
    for m in modes:
        for b in BOXES:
            pairs = ev["scores"][m][b]["pairs"]
            seg = np.array([dims[p["seg_level"]] for p in pairs])
            rows.append([m, b, f"{np.median(seg):.0f}", f"{np.mean(seg == dims[-1]) * 100:.0f}",
                         f"{np.mean(seg == dims[0]) * 100:.0f}", f"{np.percentile(seg, 25):.0f}-{np.percentile(seg, 75):.0f}"])
    return markdown_table(["mode", "box", "median d (segmentation)", "% pairs at d = D", "% pairs at the first scale",
                           "interquartile d"], rows, ["l", "l", "r", "r", "r", "r"])


def _cos_names(result: Mapping) -> list[str]:
    for r in result["runs"].values():
        if r.get("cosine"):
            return list(r["cosine"]["levels"])
    return []


def _cos_cells(cos: Optional[Mapping], key: str = "cosine") -> list[str]:
    """``key`` = "cosine" (mean over pixels) or "region_cosine" (mean over (view, region))."""
    if not cos:
        return []
    return [("-" if v.get(key) is None else f"{v[key]:.3f}") for v in cos["levels"].values()]


def _cosine_table(result: Mapping, variant_runs: Mapping[str, str]) -> str:
    from .reports import markdown_table

    names = _cos_names(result)
    rows = []
    for v, name in variant_runs.items():
        r = result["runs"][name]
        if r.get("cosine") and v in ("nested", "flat", "levels", "mlp"):
            rows.append([VARIANTS[v].title] + _cos_cells(r["cosine"]) + _cos_cells(r["cosine"], "region_cosine")
                        + [f"{r['final_loss']:.5f}"])
    if not rows:
        return "Not computed.\n"
    # Pixel means weigh a level's regions by their area (at the group level the room, floor and
    # wall, is most of the image); region means weigh every (view, region) alike. Both are shown.
    return markdown_table(["variant"] + [f"cos {n} (pixels)" for n in names]
                          + [f"cos {n} (regions)" for n in names] + ["final train loss"], rows)


# ------------------------------------------------------------------------------ CLI
def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (bench.md, bench.json, runs/, data/)")
    p.add_argument("--scene", default=None, metavar="DIR",
                   help="demo scene folder (default: generate the default demo scene into OUT/data/scene)")
    p.add_argument("--gaussians", default=None, metavar="PLY",
                   help="fitted Gaussians of the scene (default: fit them into OUT/data/gaussians)")
    p.add_argument("--bank", default=None, metavar="DIR",
                   help="segment bank of the scene (default: build it into OUT/data/bank: ground-truth "
                        "segments, caption embeddings)")
    p.add_argument("--iterations", type=positive_int, default=None, help="training steps per variant (default 1000; quick 150)")
    p.add_argument("--dim", type=positive_int, default=None,
                   help="feature dims D of every field (default 128; quick 32; paper 512). k is scaled to "
                        "keep each paper setting's number of scales")
    p.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=None, metavar="NAME",
                   help=f"variants to run (default all: {' '.join(VARIANTS)})")
    p.add_argument("--temperatures", nargs="+", type=positive_float, default=None, metavar="T",
                   help="composite temperatures evaluated on the N2F2 run (default 1 0.1 0.01; 1 = paper)")
    p.add_argument("--scale-measure", choices=list(SCALE_MEASURES), default=None,
                   help="segment scale measure of the bank the bench builds (default extent, as the cpu "
                        "pipeline; eigenvalue = the paper's)")
    p.add_argument("--scale-jitter", type=nonneg_float, default=None,
                   help="TrainConfig.scale_jitter of every run (default 0.03, as the cpu preset; 0 = the paper)")
    p.add_argument("--quick", action="store_true",
                   help="a few minutes: small generated scene, D = 32, 150 steps")
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "bench", help="reproduce the paper's ablations on the demo scene (bench.md)",
        description="Train N2F2 and its ablations (non-nested, 3-level LangSplat-like, step sizes k, MLP "
                    "backbone) on the built-in demo scene, evaluate them with LangSplat's protocol (exact and "
                    "scaled box), time the query modes, and write OUT/bench.md, OUT/bench.json and plots. "
                    "Reruns reuse finished runs and evaluations.")
    _add_arguments(p)
    p.set_defaults(func=_cmd_bench)


def _cmd_bench(args: argparse.Namespace) -> int:
    over: dict[str, Any] = {"device": args.device, "progress": not args.quiet}
    for name in ("iterations", "dim"):
        value = getattr(args, name)
        if value is not None:
            if value < 1:
                raise InputError(None, f"--{name} must be >= 1, got {value}")
            over[name] = value
    if args.variants:
        over["variants"] = tuple(args.variants)
    if args.temperatures:
        over["temperatures"] = tuple(args.temperatures)
    for name in ("scale_measure", "scale_jitter"):
        if getattr(args, name) is not None:
            over[name] = getattr(args, name)
    try:
        config = BenchConfig.quick(**over) if args.quick else BenchConfig(**over)
    except ValueError as e:
        raise InputError(None, str(e)) from None
    run_bench(args.out, config, scene=args.scene, gaussians=args.gaussians, bank=args.bank,
              log=(lambda s: None) if args.quiet else print)
    print(f"bench: {Path(args.out) / 'bench.md'}")
    return 0


def main(argv: Optional[list[str]] = None) -> int:
    """``n2f2 bench`` without the rest of the CLI (``python -m n2f2.eval.bench``)."""
    import sys

    from ..errors import N2F2Error

    p = OneLineArgumentParser(prog="n2f2 bench")
    _add_arguments(p)
    try:
        args = p.parse_args(argv)
    except SystemExit as e:  # a bad option: its one line is printed already
        return int(e.code or 0)
    try:
        return _cmd_bench(args)
    except N2F2Error as e:
        print(f"n2f2 bench: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
