"""Feature-field optimisation with hierarchical supervision (paper Sec. 3.2, appendix
"Feature Field Optimization" and "Deferred rendering").

One step:

1. sample ``pixels_per_step`` pixels uniformly over the segment-covered pixels of the training
   views and, per pixel, one covering segment with probability ∝ 1 / log(area)
   (:mod:`n2f2.train.sampling`); with ``every_segment`` (not in the paper), every covering
   segment instead, weighted by the probability of that draw;
2. **deferred rendering** (default): query the backbone at the (frozen) Gaussian centres,
   render those low-dimensional features (F = TriPlane channels) at the sampled pixels and run
   the MLP there, giving ``theta(u) [P, D]``. Without deferral the MLP runs per Gaussian and D
   channels are rendered (what test time does). Rendering is either rasterizing
   ``views_per_step`` random views every step (pixels are then sampled from those views), or,
   with ``blend_cache`` (CPU preset), gathering the sampled pixels' entries of per-view blending
   weights computed once (:mod:`n2f2.train.blend`; exact, since the Gaussians are frozen), with
   pixels sampled across all training views every step;
3. ``phi = W (B(s) * theta)`` with the variant's mask B(s); loss ``L2 + lambda * (1 - cos)``
   (computed in the field's D dims, :func:`projected_loss`); Adam, TriPlane at
   ``0.0016 x scene extent``, MLP and W at ``0.00125``.

Checkpoints (``RUN/checkpoint.pt``: field + W + config + optimiser + step + sampler RNG + loss
curve) are written atomically every ``checkpoint_every`` steps; ``resume=True`` continues from
the saved step with exactly the saved state, so an interrupted run ends where an uninterrupted
one would.

A step whose loss or gradient is not finite is skipped (no update; counted as
``skipped_steps``); :data:`~n2f2.validate.MAX_BAD_STEPS` of them in a row stop the run with a
:class:`~n2f2.validate.NonFiniteError`. Nothing holding NaN or infinity is ever saved.

The settings are :class:`~n2f2.train.config.TrainConfig`; the loss is in :mod:`n2f2.train.losses`,
theta(u) at the sampled pixels in :mod:`n2f2.train.geometry`, and reading a checkpoint in
:mod:`n2f2.train.checkpoint`.
"""

from __future__ import annotations

import resource
import shutil
import time
from dataclasses import dataclass, fields
from dataclasses import field as dc_field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Optional, Union

import numpy as np
import torch
from torch import Tensor

from ..errors import InputError
from ..field.model import FieldConfig, NestedField, bbox_from_points, save_field
from ..io import make_dirs, save_torch, write_json
from ..segments.bins import ONE_MINUS_EPS
from ..validate import MAX_BAD_STEPS, NonFiniteError, check_finite, finite_array
from .blend import BlendCache, build_blend_cache
from .checkpoint import CHECKPOINT_FORMAT, load_checkpoint
from .config import CHECKPOINT_NAME, FIELD_NAME, GAUSSIANS_NAME, LIFT_NAME, REPORT_NAME, TrainConfig
from .geometry import bank_cameras, frozen_geometry, pixel_theta, split_views
from .losses import prefix_projected_loss, projected_loss
from .sampling import PixelBatch, SegmentPool, ViewSegments

if TYPE_CHECKING:
    from ..data.scene import Scene
    from ..gaussians.model import Gaussians
    from ..segments.bank import SegmentBank


def jitter_scales(
    scale: Tensor,  # [P] quantized scales in [0, 1)
    amount: float,
    generator: torch.Generator,
) -> Tensor:  # [P]
    """``scale`` plus uniform noise in [-amount, amount], kept in [0, 1) (TrainConfig.scale_jitter).
    ``amount == 0`` returns ``scale`` itself and draws nothing, so the random stream (and a
    run) stays the paper's."""
    if amount <= 0:
        return scale
    noise = torch.rand(scale.shape, generator=generator, dtype=scale.dtype) * 2 - 1
    return (scale + amount * noise).clamp(0.0, ONE_MINUS_EPS)


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _view_segments(bank: Any, views: list[int], cameras: list, show_progress: bool) -> dict[int, ViewSegments]:
    from tqdm import tqdm

    out = {}
    for v in tqdm(views, desc="loading segments", disable=not show_progress, leave=False):
        record = bank.record(v)
        name = f"{bank.image_names[v]}/embeddings.npy"  # a bank written before imports were checked
        finite_array(Path(getattr(bank, "root", ".")) / name, name, record.embeddings)
        out[v] = ViewSegments.from_record(v, record, (cameras[v].height, cameras[v].width))
    return out


@dataclass
class _Run:
    """What a training run reads and never changes: its settings, where it writes, the frozen
    Gaussians, and the segments its steps sample from."""

    config: TrainConfig
    field_config: FieldConfig
    E: int  # teacher embedding size
    device: torch.device
    out: Path
    ck_path: Path
    paths: dict  # {"scene", "gaussians", "bank"}: recorded in meta
    bank: SegmentBank
    meta: dict  # recorded in the checkpoint and in field.pt
    bbox_min: np.ndarray  # [3]
    bbox_max: np.ndarray  # [3]
    train_views: list[int]
    test_views: list[int]
    extent: float
    cameras: list  # per scene view, at the bank's resolution over render_downscale
    geometry: dict[str, Tensor]  # frozen_geometry of the Gaussians
    segments: dict[int, ViewSegments]  # per training view
    usable: list[int]  # training views with a pixel covered by a segment
    cache: Optional[BlendCache]
    cache_info: dict  # for the report
    encoder: Callable[[], Tensor]  # the field's backbone at the (frozen) Gaussian centres
    every_view: bool  # every step draws pixels across all usable views
    pool_all: Optional[SegmentPool]  # their segments, when every_view


@dataclass
class _State:
    """What the loop carries from step to step; a checkpoint saves all of it but this session's
    timings and row count."""

    field: NestedField
    optimizer: torch.optim.Optimizer
    generator: torch.Generator  # every random draw of the sampling
    step: int
    curve: dict[str, list]  # "step", "loss", "l2", "cos" every log_every steps
    train_time: float
    skipped: int  # steps skipped for a non-finite loss or gradient, in all
    # Losses since the last curve point (checkpointed, so a resumed curve equals an uninterrupted one).
    window: list[tuple[float, ...]]
    bad_run: int = 0  # skipped steps in a row
    supervised_rows: int = 0  # (pixel, segment) rows over this session's steps
    iter_times: list[float] = dc_field(default_factory=list)
    # Process CPU time (all threads): robust to other processes' load.
    cpu_times: list[float] = dc_field(default_factory=list)


def train_field(
    scene: Scene,
    gaussians: Gaussians,  # frozen
    bank: SegmentBank,
    out_dir: Union[str, Path],
    *,
    field_config: Optional[FieldConfig] = None,
    config: Optional[TrainConfig] = None,
    resume: bool = False,
    paths: Optional[dict] = None,  # {"scene", "gaussians", "bank"}: recorded in meta
    progress: bool = True,
    callback: Optional[Callable[[int, float], None]] = None,  # after each step: (step, loss)
    skip_missing: bool = False,  # the scene was loaded without its missing images: so is it for renders
) -> dict:
    """Optimise the nested feature field; writes ``field.pt``, ``checkpoint.pt`` and
    ``train_report.json`` in ``out_dir`` and returns the report."""
    from tqdm import tqdm

    out = Path(out_dir)
    paths = {k: (None if v is None else str(v)) for k, v in (paths or {}).items()}
    config = config or TrainConfig.cpu()
    field_config = field_config or FieldConfig()
    device = torch.device(config.device)
    bank_path = paths.get("bank")
    bank.validate_against(scene)  # a bank of another scene (image count, names, sizes): InputError
    E = int(bank.embed_dim)
    ck_path = out / CHECKPOINT_NAME
    checkpoint = _resumed_checkpoint(ck_path, paths, E, field_config, gaussians) if resume else None

    train_views, test_views = split_views(scene, config.holdout)
    cameras = _training_cameras(scene, bank, config.render_downscale)
    geometry = frozen_geometry(gaussians, device)
    extent = float(scene.extent())
    if checkpoint is not None:
        bbox_min, bbox_max = (
            np.asarray(checkpoint["field_meta"]["bbox_min"]),
            np.asarray(checkpoint["field_meta"]["bbox_max"]),
        )
    else:
        bbox_min, bbox_max = bbox_from_points(geometry["means"])
    state = _initial_state(config, field_config, E, bbox_min, bbox_max, extent, device, checkpoint)
    meta = {
        "encoder_spec": getattr(bank, "encoder_spec", None),
        "scene": paths.get("scene") or str(getattr(scene, "root", "")),
        "downscale": float(getattr(scene, "downscale", 1.0)),  # as loaded: renders of the run use it too
        "skip_missing": bool(skip_missing),
        "gaussians": paths.get("gaussians"),
        "bank": bank_path,
        "scene_extent": extent,
        "num_gaussians": int(geometry["means"].shape[0]),
        "bank_size": [int(bank.width), int(bank.height)],
        "train_views": train_views,
        "heldout_views": test_views,
    }

    segments = _view_segments(bank, train_views, cameras, progress)
    usable = [v for v in train_views if len(segments[v].covered)]
    if not usable:
        raise InputError(bank_path, "no training view has a pixel covered by a valid segment")
    cache, cache_info = _blend_cache(config, geometry, cameras, usable, progress)
    # Pixels drawn across all training images (blend cache: every view is at hand each step).
    every_view = cache is not None or config.views_per_step >= len(usable)
    run = _Run(
        config=config,
        field_config=field_config,
        E=E,
        device=device,
        out=out,
        ck_path=ck_path,
        paths=paths,
        bank=bank,
        meta=meta,
        bbox_min=bbox_min,
        bbox_max=bbox_max,
        train_views=train_views,
        test_views=test_views,
        extent=extent,
        cameras=cameras,
        geometry=geometry,
        segments=segments,
        usable=usable,
        cache=cache,
        cache_info=cache_info,
        encoder=state.field.fixed_point_encoder(geometry["means"]),  # the centres are frozen
        every_view=every_view,
        pool_all=SegmentPool.from_views([segments[v] for v in usable], config.pixel_balance) if every_view else None,
    )

    make_dirs(out)
    bar = tqdm(
        total=config.iterations,
        initial=min(state.step, config.iterations),
        desc="train field",
        disable=not progress,
        dynamic_ncols=True,
    )
    state.field.train()
    while state.step < config.iterations:
        _step(run, state, bar, callback)
    bar.close()
    if state.iter_times and state.bad_run == len(state.iter_times):
        raise _stopped(state.step, f"all {state.bad_run} steps of this run")
    return _finish(run, state)


def _resumed_checkpoint(ck_path: Path, paths: dict, E: int, field_config: FieldConfig, gaussians: Gaussians) -> dict:
    """The checkpoint to resume from, checked against this run's bank, field config and
    Gaussians (InputError naming the file that disagrees)."""
    if not ck_path.is_file():
        raise InputError(ck_path, "no checkpoint to resume from (run without --resume to start)")
    checkpoint = load_checkpoint(ck_path)
    fmeta = checkpoint["field_meta"]
    if int(fmeta["embed_dim"]) != E:
        raise InputError(
            paths.get("bank"),
            f"segment bank embeddings have dim {E} but the checkpoint "
            f"{ck_path} was trained with E = {fmeta['embed_dim']} "
            f"(encoder {fmeta.get('encoder_spec')!r})",
        )
    saved = FieldConfig.from_dict(fmeta["config"])
    if saved != field_config:
        raise InputError(ck_path, f"checkpoint field config {saved} differs from the requested {field_config}")
    if int(checkpoint["num_gaussians"]) != int(gaussians.means.shape[0]):
        raise InputError(
            paths.get("gaussians"),
            f"the checkpoint was trained on {checkpoint['num_gaussians']} "
            f"Gaussians, this model has {gaussians.means.shape[0]}",
        )
    return checkpoint


def _training_cameras(scene: Scene, bank: SegmentBank, render_downscale: int) -> list:
    """The scene's cameras at the bank's resolution, downscaled by ``render_downscale``."""
    if render_downscale < 1 or render_downscale != int(render_downscale):
        raise ValueError(f"render_downscale must be a positive integer, got {render_downscale}")
    return [c.downscaled(render_downscale) if render_downscale > 1 else c for c in bank_cameras(scene, bank)]


def _initial_state(
    config: TrainConfig,
    field_config: FieldConfig,
    E: int,
    bbox_min: np.ndarray,  # [3]
    bbox_max: np.ndarray,  # [3]
    extent: float,
    device: torch.device,
    checkpoint: Optional[dict],
) -> _State:
    """A field and its optimiser seeded with ``config.seed``, continued from ``checkpoint``'s
    state when there is one."""
    torch.manual_seed(config.seed)  # initial TriPlane / MLP weights
    field = NestedField(field_config, E, bbox_min, bbox_max).to(device)
    # Fused Adam (one kernel for all parameters): ~10x faster on CPU than the per-tensor loop.
    optimizer = torch.optim.Adam(field.param_groups(config.lr_triplane * extent, config.lr_mlp), fused=True)
    generator = torch.Generator().manual_seed(config.seed)
    state = _State(field, optimizer, generator, 0, {"step": [], "loss": [], "l2": [], "cos": []}, 0.0, 0, [])
    if checkpoint is not None:
        field.load_state_dict(checkpoint["field_state"])
        optimizer.load_state_dict(checkpoint["optimizer"])
        generator.set_state(checkpoint["rng"])
        state.step, state.curve = int(checkpoint["step"]), checkpoint["curve"]
        state.train_time = float(checkpoint["train_time"])
        state.skipped = int(checkpoint.get("skipped", 0))
        state.window = [tuple(w) for w in checkpoint.get("window", [])]
    return state


def _blend_cache(
    config: TrainConfig, geometry: dict[str, Tensor], cameras: list, usable: list[int], progress: bool
) -> tuple[Optional[BlendCache], dict]:
    """The usable views' blending weights with ``config.blend_cache`` (None when it would not
    fit in ``blend_cache_mb``: large scenes rasterize every step instead), and what the report
    says of them."""
    cache, cache_info = None, {"used": False}
    if config.blend_cache:
        t0 = time.perf_counter()
        try:
            cache = build_blend_cache(
                geometry, [cameras[v] for v in usable], max_bytes=config.blend_cache_mb * 2**20, progress=progress
            )
            cache_info = {
                "used": True,
                "mb": cache.nbytes / 2**20,
                "build_s": time.perf_counter() - t0,
                "entries_per_pixel": int(cache.gid.numel()) / max(1, int(cache.crow.numel()) - 1),
            }
        except MemoryError as e:
            cache_info = {"used": False, "reason": str(e)}
    return cache, cache_info


def _batch_loss(run: _Run, state: _State) -> tuple[Tensor, Tensor, Tensor]:
    """Sample one step's (pixel, segment) rows, render theta(u) at their pixels and return
    ``(loss, l2, cos)`` of phi against the segments' embeddings."""
    config, device, field, generator = run.config, run.device, state.field, state.generator
    if run.every_view:
        views, pool = run.usable, run.pool_all
    else:  # only the views rasterized this step
        views = [
            run.usable[i]
            for i in torch.randperm(len(run.usable), generator=generator)[: config.views_per_step].tolist()
        ]
        pool = SegmentPool.from_views([run.segments[v] for v in views], config.pixel_balance)
    assert pool is not None  # pool_all is built whenever every_view is set
    if config.every_segment:
        batch = pool.sample_every_segment(config.pixels_per_step, generator)
    else:
        batch = pool.sample(config.pixels_per_step, generator)
    theta = pixel_theta(
        field,
        run.geometry,
        _to(batch, device),
        config.deferred,
        cameras=[run.cameras[v] for v in views],
        cache=run.cache,
        encoder=run.encoder,
    )
    scale = jitter_scales(batch.scale, config.scale_jitter, generator)
    state.supervised_rows += len(batch.row)
    ids, index = torch.unique(batch.pooled, return_inverse=True)
    targets = pool.embeddings[ids].to(device)
    scale, index = scale.to(device), index.to(device)
    if config.every_segment and field.kind.prefix:  # weighted rows, prefix masks
        rows, weight = batch.row.to(device), batch.weight.to(device)
        return prefix_projected_loss(
            theta, rows, field.dims_for_scale(scale), field.W, targets, index, config.cos_weight, weight
        )
    # One row per pixel (the paper), or weighted rows with the 3-level field's block masks.
    x = theta.index_select(0, batch.row.to(device)) if config.every_segment else theta
    weight = batch.weight.to(device) if config.every_segment else None
    x = x * field.supervision_mask(scale)
    return projected_loss(x, field.W, targets, index, config.cos_weight, weight)


def _step(run: _Run, state: _State, bar: Any, callback: Optional[Callable[[int, float], None]]) -> None:
    """One optimisation step, skipped (no update) when its loss or a gradient is not finite,
    then its bookkeeping: timings, the loss curve, the progress bar, a checkpoint every
    ``checkpoint_every`` steps, and ``callback``."""
    config = run.config
    t0, c0 = time.perf_counter(), time.process_time()
    loss, l2, cos = _batch_loss(run, state)
    state.optimizer.zero_grad(set_to_none=True)
    loss.backward()
    finite = _finite_step(loss, state.field.parameters())
    if finite:
        state.optimizer.step()
        state.bad_run = 0
    else:  # no update: the field and the optimiser state stay as they were
        state.skipped += 1
        state.bad_run += 1
        if state.bad_run >= MAX_BAD_STEPS:
            bar.close()
            raise _stopped(state.step + 1, f"the last {state.bad_run} steps")
    state.step += 1
    dt = time.perf_counter() - t0
    state.train_time += dt
    state.iter_times.append(dt)
    state.cpu_times.append(time.process_time() - c0)
    values = (loss.item(), l2.item(), cos.item())
    if finite:
        state.window.append(values)
    if (state.step % config.log_every == 0 or state.step == config.iterations) and state.window:
        m = np.mean(state.window, axis=0)
        for key, value in zip(("loss", "l2", "cos"), m):
            state.curve[key].append(float(value))
        state.curve["step"].append(state.step)
        state.window.clear()
        bar.set_postfix(loss=f"{m[0]:.4g}", cos=f"{1 - m[2]:.3f}")
    bar.update(1)
    if config.checkpoint_every and state.step % config.checkpoint_every == 0 and state.step < config.iterations:
        _save_checkpoint(run, state)
    if callback is not None:
        callback(state.step, values[0])


def _checkpoint_blob(run: _Run, state: _State) -> dict:
    """Everything a resumed run needs to end where an uninterrupted one would."""
    return {
        "format": CHECKPOINT_FORMAT,
        "step": state.step,
        "field_state": {k: v.detach().cpu().clone() for k, v in state.field.state_dict().items()},
        "field_meta": {
            **run.meta,
            "config": run.field_config.to_dict(),
            "embed_dim": run.E,
            "bbox_min": list(map(float, run.bbox_min)),
            "bbox_max": list(map(float, run.bbox_max)),
        },
        "optimizer": state.optimizer.state_dict(),
        "rng": state.generator.get_state(),
        "train_config": run.config.to_dict(),
        "curve": state.curve,
        "window": list(state.window),
        "train_time": state.train_time,
        "num_gaussians": int(run.geometry["means"].shape[0]),
        "skipped": state.skipped,
    }


def _save_checkpoint(run: _Run, state: _State) -> None:
    blob = _checkpoint_blob(run, state)
    check_finite(run.ck_path, {"field_state": blob["field_state"], "optimizer": blob["optimizer"]["state"]})
    save_torch(run.ck_path, blob, keep=True)  # resumable state: kept if the command fails


def _finish(run: _Run, state: _State) -> dict:
    """Write the last checkpoint, ``field.pt``, the lift (when asked for) and
    ``train_report.json``; return the report."""
    config, out, field = run.config, run.out, state.field
    _save_checkpoint(run, state)
    field.eval()
    check_finite(out / FIELD_NAME, field.state_dict())
    gpath = _record_gaussians(run.paths.get("gaussians"), out)
    field_meta = {**run.meta, "gaussians": gpath, "step": state.step, "train_config": config.to_dict()}
    save_field(out / FIELD_NAME, field, field_meta)
    lift_info: dict = {"written": False}
    if config.lift and run.cache is not None and config.render_downscale == 1:
        from ..field.lift import lift_features, save_lift

        lift = lift_features(run.cache, run.usable, run.bank, int(run.geometry["means"].shape[0]))
        save_lift(out / LIFT_NAME, lift, {"bank": run.paths.get("bank"), "gaussians": gpath})
        lift_info = {
            "written": True,
            "path": str(out / LIFT_NAME),
            "seconds": lift.seconds["lift"],
            "blend_weights_s": run.cache_info.get("build_s"),
        }
    iter_times, cpu_times = state.iter_times, state.cpu_times
    report = {
        "steps": state.step,
        "variant": run.field_config.variant,
        "deferred": config.deferred,
        "blend_cache": run.cache_info,
        "lift": lift_info,
        "field_config": run.field_config.to_dict(),
        "train_config": config.to_dict(),
        "embed_dim": run.E,
        "num_gaussians": run.meta["num_gaussians"],
        "train_views": run.train_views,
        "heldout_views": run.test_views,
        "scene_extent": run.extent,
        "final_loss": state.curve["loss"][-1] if state.curve["loss"] else None,
        "skipped_steps": state.skipped,
        "train_time_s": state.train_time,
        # This session's iterations only (a resumed run measures what it ran).
        "time_per_iteration_s": float(np.median(iter_times)) if iter_times else None,
        "cpu_time_per_iteration_s": float(np.median(cpu_times)) if cpu_times else None,
        # Supervised (pixel, segment) rows per step: pixels_per_step unless every_segment.
        "rows_per_iteration": state.supervised_rows / len(iter_times) if iter_times else None,
        "threads": torch.get_num_threads(),
        "peak_rss_mb": _peak_rss_mb(),
        "curve": state.curve,
        "paths": {**run.paths, "gaussians": gpath},
    }
    write_json(out / REPORT_NAME, report)
    return report


def _stopped(step: int, which: str) -> NonFiniteError:
    return NonFiniteError(
        None,
        f"training stopped at step {step}: {which} had a NaN or infinite loss or "
        "gradient and were skipped (nothing non-finite was saved); check the segment "
        "bank's embeddings and the loss options (--cos-weight, --pixels-per-step)",
    )


def _finite_step(loss: Tensor, params: Any) -> bool:
    """Whether the loss and every parameter's gradient are finite, from one sum over all of
    them: NaN and infinity propagate through it (a sum of finite gradients so large that it
    overflows counts as non-finite too). Much cheaper than ``isfinite(...).all()`` per tensor:
    0.8 vs 14 ms for the cpu preset field's 1.7M parameters on one (shared) core."""
    sums = [loss.detach().float().sum()] + [p.grad.sum() for p in params if p.grad is not None]
    return bool(torch.isfinite(torch.stack(sums).sum()))


def _to(batch: PixelBatch, device: torch.device) -> PixelBatch:
    return PixelBatch(*(getattr(batch, f.name).to(device) for f in fields(PixelBatch)))


def _record_gaussians(path: Optional[str], out: Path) -> Optional[str]:
    """Copy the PLY the field was trained on into the run folder (so RUN/ is self-contained),
    and the learned background its fit saved beside it (``background.json``): renders of the
    run composite RGB over it as the fit's own test views do (a background left there by other
    Gaussians goes)."""
    if not path:
        return None
    from ..gaussians.fit import BACKGROUND_NAME
    from ..io import atomic_path, remove_results

    src, dst = Path(path), out / GAUSSIANS_NAME
    if src.resolve() != dst.resolve():  # (the run's own copy has its background beside it)
        with atomic_path(dst) as tmp:
            shutil.copyfile(src, tmp)
        if (src.parent / BACKGROUND_NAME).is_file():
            with atomic_path(out / BACKGROUND_NAME) as tmp:
                shutil.copyfile(src.parent / BACKGROUND_NAME, tmp)
        else:  # the fit rendered on black
            remove_results(out, [BACKGROUND_NAME])
    return str(dst)
