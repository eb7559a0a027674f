"""Evaluation of the bench's runs through the evaluation's runner (:func:`n2f2.eval.stage.run_eval`,
as ``n2f2 eval`` scores a run): LangSplat's protocol (both box sizes), the per-level cosine to
the teacher, and statistics of the composite weights gamma. Each result is cached in its run
folder's ``stages.json``, keyed on the content of the field and the labels
(:class:`n2f2.pipeline.cache.StageCache`). The training-free lift is scored by the same runner
through a :class:`n2f2.query.lifted.LiftEngine` (:func:`evaluate_lift`), as ``n2f2 eval
--budget`` scores it (:func:`n2f2.eval.budget.loss_budget`). Every run, the lift included, is
also scored under the 3D protocol (``--protocol 3d``, every 3D mode it answers;
:func:`evaluate_variant_3d`, :func:`evaluate_lift_3d`) into ``RUN/eval3d/``, cached the same
way."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Mapping, Optional, Sequence

from ..eval.stage import run_eval

if TYPE_CHECKING:
    from ..eval.job import EvalJob
    from .config import BenchConfig, BenchData


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


def evaluate_variant(
    run_dir: Path,
    data: "BenchData",
    modes: Sequence[str],
    out_dir: Path,
    config: "BenchConfig",
    temperature: float = 1.0,
    log: Callable[[str], None] = print,
    encoder: Any = None,
    render: Optional[str] = None,  # QueryConfig.render ("gaussians": the paper's test-time form); None: its default
    weights: str = "eq6",  # QueryConfig.composite_weights: the bench's rows are the paper's Eq. 6 unless named
) -> dict:
    """``evaluate_run`` of one run (both box sizes), written to ``out_dir`` (eval.json and eval.md;
    the bench draws its own plots); reused while the field, the labels, the modes, the composite
    weights and T and the rendering are unchanged."""
    from ..eval.runner import load_eval
    from ..pipeline.cache import StageCache, file_digest, stage_key, tree_digest
    from ..query.engine import DEFAULT_RENDER

    render = render or DEFAULT_RENDER

    eval_json = out_dir / "eval.json"
    key = stage_key(
        field=file_digest(run_dir / "field.pt"),
        labels=tree_digest(data.label_dir),
        bank=file_digest(data.bank_dir / "bank.json"),
        modes=list(modes),
        temperature=temperature,
        render=render,  # evaluations cached before deferred views (no key) are redone
        weights=weights,
    )
    cache = StageCache.open(run_dir)
    cache.run(
        out_dir.name,
        key,
        [eval_json],
        lambda: _evaluate(
            run_dir, data, modes, out_dir, config, temperature, encoder, render, weights, _prefixed(run_dir, log)
        ),
        log=_prefixed(run_dir, log),
    )
    return load_eval(eval_json)


def _evaluate(
    run_dir: Path,
    data: "BenchData",
    modes: Sequence[str],
    out_dir: Path,
    config: "BenchConfig",
    temperature: float,
    encoder: Any,
    render: str,
    weights: str,
    log: Callable[[str], None],
) -> None:
    """The 2D protocol on one run through the evaluation's runner, as ``n2f2 eval`` writes it."""
    from ..query.engine import QueryConfig

    job = _bench_job(
        run_dir,
        data,
        out_dir,
        config,
        modes=tuple(modes),
        query_config=QueryConfig(temperature=temperature, render=render, composite_weights=weights),
        encoder=encoder,
        bank=data.bank_dir,
        notes=(
            f"bench: composite weights {weights} (temperature T = {temperature:g} for eq6), 2D views rendered {render}",
        ),
    )
    run_eval(job, log=log)


def _bench_job(run_dir: Path, data: "BenchData", out_dir: Path, config: "BenchConfig", **fields: Any) -> "EvalJob":
    """An evaluation of the bench's labels into ``out_dir``: the bench's scene and bank, no
    relevancy files, and what the stage cache chose to redo replaced."""
    from ..eval.job import EvalJob

    return EvalJob(
        run_dir=run_dir,
        labels=data.label_dir,
        out=out_dir,
        scene=data.scene_dir,
        relevancy=False,
        force=True,
        device=config.device,
        progress=config.progress,
        **fields,
    )


def evaluate_lift(
    run_dir: Path,
    lift: Mapping[str, Any],
    data: "BenchData",
    modes: Sequence[str],
    out_dir: Path,
    config: "BenchConfig",
    log: Callable[[str], None] = print,
    encoder: Any = None,
) -> dict:
    """``evaluate_run`` of the lift variant (``lift``: what
    :func:`n2f2.experiments.training.lift_variant` returned), written to ``out_dir`` as
    :func:`evaluate_variant` writes a field's; reused while the lift, its Gaussians, the labels
    and the modes are unchanged."""
    from ..eval.runner import load_eval
    from ..pipeline.cache import StageCache, file_digest, stage_key, tree_digest

    eval_json = out_dir / "eval.json"
    key = stage_key(
        lift=file_digest(Path(lift["lift_path"])),
        gaussians=file_digest(Path(lift["gaussians"])),
        source=lift.get("source_run"),
        labels=tree_digest(data.label_dir),
        bank=file_digest(data.bank_dir / "bank.json"),
        modes=list(modes),
    )
    StageCache.open(run_dir).run(
        out_dir.name,
        key,
        [eval_json],
        lambda: _evaluate_lift(lift, data, modes, out_dir, config, encoder, _prefixed(run_dir, log)),
        log=_prefixed(run_dir, log),
    )
    return load_eval(eval_json)


def _lift_engine(lift: Mapping[str, Any], data: "BenchData", config: "BenchConfig", encoder: Any) -> tuple[Any, Path]:
    """The lift's query engine built as the loss budget builds it (the source run's Gaussians and
    field metadata when a trained run holds the lift), and the run folder it reports."""
    from ..data import load_scene
    from ..field.lift import load_lift
    from ..gaussians import read_ply
    from ..query.engine import QueryConfig, QueryEngine
    from ..query.lifted import lift_engine

    query_config = QueryConfig()
    if lift.get("source_run"):
        run_dir = Path(lift["source_run"])
        base = QueryEngine.from_run(
            run_dir, device=config.device, scene=data.scene_dir, config=query_config, encoder=encoder
        )
        gaussians, meta, scene = base.gaussians, dict(base.meta), base.scene
    else:  # built by the bench from its own Gaussians: no run holds them
        run_dir = Path(lift["lift_path"]).parent
        gaussians = read_ply(lift["gaussians"], device=config.device)
        meta, scene = dict(lift["meta"]), load_scene(data.scene_dir)
    features = load_lift(lift["lift_path"], num_gaussians=int(gaussians.means.shape[0]))
    return lift_engine(features, gaussians, encoder, meta, query_config, config.device, scene, run_dir), run_dir


def _evaluate_lift(
    lift: Mapping[str, Any],
    data: "BenchData",
    modes: Sequence[str],
    out_dir: Path,
    config: "BenchConfig",
    encoder: Any,
    log: Callable[[str], None],
) -> None:
    """The lift's query engine (:func:`_lift_engine`) scored by the evaluation's runner."""
    engine, run_dir = _lift_engine(lift, data, config, encoder)
    job = _bench_job(
        run_dir,
        data,
        out_dir,
        config,
        modes=tuple(modes),
        query_config=engine.config,
        encoder=encoder,
        engine=engine,
        bank=data.bank_dir,
        notes=(f"bench: the training-free lift {lift['lift_path']} ({lift['about']})",),
    )
    run_eval(job, log=log)


def evaluate_variant_3d(
    run_dir: Path,
    data: "BenchData",
    out_dir: Path,
    config: "BenchConfig",
    log: Callable[[str], None] = print,
    encoder: Any = None,
) -> dict:
    """The 3D protocol on one trained run (every 3D mode its field answers, composite at T = 1),
    written to ``out_dir`` (eval.json and eval.md as ``n2f2 eval --protocol 3d`` writes them);
    reused while the field, its Gaussians, the labels and the protocol's settings are unchanged."""
    from ..pipeline.cache import file_digest

    def engine() -> Any:
        from ..query.engine import QueryConfig, QueryEngine

        return QueryEngine.from_run(
            run_dir, device=config.device, scene=data.scene_dir, config=QueryConfig(), encoder=encoder
        )

    inputs = {"field": file_digest(run_dir / "field.pt"), "gaussians": file_digest(run_dir / "gaussians.ply")}
    return _cached_3d(run_dir, inputs, engine, data, out_dir, config, log)


def evaluate_lift_3d(
    run_dir: Path,
    lift: Mapping[str, Any],
    data: "BenchData",
    out_dir: Path,
    config: "BenchConfig",
    log: Callable[[str], None] = print,
    encoder: Any = None,
) -> dict:
    """The 3D protocol on the lift (its engine built as :func:`evaluate_lift` builds it), written
    and reused as :func:`evaluate_variant_3d`'s."""
    from ..pipeline.cache import file_digest

    inputs = {
        "lift": file_digest(Path(lift["lift_path"])),
        "gaussians": file_digest(Path(lift["gaussians"])),
        "source": lift.get("source_run"),
    }
    return _cached_3d(run_dir, inputs, lambda: _lift_engine(lift, data, config, encoder)[0], data, out_dir, config, log)


def _cached_3d(
    run_dir: Path,
    inputs: Mapping[str, Any],
    engine: Callable[[], Any],
    data: "BenchData",
    out_dir: Path,
    config: "BenchConfig",
    log: Callable[[str], None],
) -> dict:
    """``evaluate_protocol3d`` of the engine ``engine()`` builds, under the run's stage cache:
    the key adds the labels, the bank (the text encoder), the protocol's settings and the
    eval.json format to ``inputs``."""
    from ..eval.protocol3d import FORMAT_3D, Protocol3dConfig
    from ..pipeline.cache import StageCache, file_digest, stage_key, tree_digest

    eval_json = out_dir / "eval.json"
    settings = {k: v for k, v in asdict(Protocol3dConfig()).items() if k != "progress"}
    key = stage_key(
        **inputs,
        labels=tree_digest(data.label_dir),
        bank=file_digest(data.bank_dir / "bank.json"),
        protocol=settings,
        format=FORMAT_3D,
    )

    def run() -> None:
        run_eval(
            _bench_job(run_dir, data, out_dir, config, protocol="3d", engine=engine()), log=_prefixed(run_dir, log)
        )

    StageCache.open(run_dir).run(out_dir.name, key, [eval_json], run, log=_prefixed(run_dir, log))
    return json.loads(eval_json.read_text())


def _prefixed(run_dir: Path, log: Callable[[str], None]) -> Callable[[str], None]:
    """``log`` with the bench's prefix naming the run."""
    return lambda line: log(f"[bench] {run_dir.name}: {line}")


def cosine_variant(run_dir: Path, data: "BenchData", config: "BenchConfig", log: Callable[[str], None] = print) -> dict:
    """Per-level cosine to the teacher on the run's held-out views (``eval_field.json``, reused
    while the field and the bank are unchanged)."""
    from ..pipeline.cache import StageCache, file_digest, stage_key

    path = run_dir / "eval_field.json"
    key = stage_key(field=file_digest(run_dir / "field.pt"), bank=file_digest(data.bank_dir / "bank.json"))
    StageCache.open(run_dir).run(
        "eval-field",
        key,
        [path],
        lambda: _cosine(run_dir, data, config, path),
        log=lambda s: log(f"[bench] {run_dir.name}: {s}"),
    )
    return json.loads(path.read_text())


def _cosine(run_dir: Path, data: "BenchData", config: "BenchConfig", path: Path) -> None:
    from ..data import load_scene
    from ..field import load_field
    from ..gaussians import read_ply
    from ..io import write_json
    from ..segments.bank import SegmentBank
    from ..train.evaluate import evaluate_cosine_by_level

    field, meta = load_field(run_dir / "field.pt", device=config.device)
    views = meta.get("heldout_views") or list(range(len(meta.get("train_views", []))))
    result = evaluate_cosine_by_level(
        field,
        read_ply(run_dir / "gaussians.ply"),
        load_scene(data.scene_dir),
        SegmentBank.open(data.bank_dir),
        views,
        device=config.device,
    )
    write_json(path, result)


def gamma_statistics(engine: Any, temperature: float) -> dict:
    """Statistics over the Gaussians of ``gamma^3D`` (paper Eq. 6) at ``temperature``: how far it
    is from uniform (max gamma x number of scales; 1 = uniform), its effective number of scales
    ``exp(entropy)``, where its mass sits (mean weight-averaged prefix length / D), and the
    prefix weights ``revcumsum(gamma)`` (paper Eq. 7) at a few dimensions."""
    import torch

    from ..query.composite import composite_weights, prefix_weights, temperature_name

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
    return {
        "temperature": temperature_name(temperature),
        "scales": S,
        "gaussians": N,
        "uniform": 1.0 / S,
        "max_gamma_mean": float(mx.mean()),
        "max_gamma_median": q(mx, 0.5),
        "max_gamma_p95": q(mx, 0.95),
        "max_gamma_max": float(mx.max()),
        "max_gamma_x_scales_mean": float(mx.mean()) * S,
        "effective_scales_mean": float(torch.exp(ent).mean()),
        "mass_centre_mean": float(centre.mean()),
        "argmax_first_scale": float((argmax == 0).double().mean()),
        "argmax_last_scale": float((argmax == S - 1).double().mean()),
        "prefix_weight_at": {str(j + 1): float(ramp[j]) for j in at},
    }
