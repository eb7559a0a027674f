"""Fit a 3D Gaussian Splatting model to posed RGB images (3DGS, Kerbl et al. 2023).

Loss ``(1 - lambda) L1 + lambda (1 - SSIM)``; Adam with the 3DGS per-parameter learning rates
(exponentially decaying position rate, scaled by the scene extent); adaptive density control
(clone small / split large Gaussians with a large view-space positional gradient, prune
transparent and huge ones, periodic opacity reset), capped at ``max_gaussians``; active SH
degree raised every ``sh_degree_interval`` steps. Optionally (the CPU preset) a depth-spread
regulariser that pulls the Gaussians a ray meets onto one depth, for better rendered depth.

Robustness: a step whose loss or gradients are not finite, or whose update would make a
parameter non-finite, is skipped (nothing changes and it is counted in the report).
Checkpoints hold everything needed to continue bit-for-bit (parameters, optimiser moments,
densification statistics, RNG state, the view order) and are written atomically, and only from
finite state.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Optional, Sequence, Union

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..data.scene import Scene
from ..errors import InputError
from ..io import load_torch, save_torch, write_json
from ..validate import MAX_BAD_STEPS, NonFiniteError
from .fit_config import (
    FitConfig,
    init_kind,
    split_views,
)
from .init import (
    background_shell,
    init_from_points,
    init_random_in_frusta,
    random_points_in_frusta,
    random_points_seen,
    uncovered_cells,
)
from .model import Gaussians, rgb_to_sh
from .optim import (
    DensifyStats,
    GaussianAdam,
    densify_and_prune,
    learning_rates,
    photometric_loss,
    psnr,
    reset_opacity,
)
from .ply import write_ply

CHECKPOINT_NAME = "checkpoint.pt"
PLY_NAME = "gaussians.ply"
REPORT_NAME = "fit_report.json"
TEST_RENDERS_DIR = "test_views"  # held-out renders beside their photos (PNG + float32 .npy)
_CHECKPOINT_FORMAT = "n2f2-gaussians-checkpoint-v1"


@dataclass
class FitReport:
    """What :func:`fit_gaussians` writes to ``fit_report.json``."""

    steps: int
    wall_time_s: float  # this invocation, including evaluation
    train_time_s: float  # optimisation time summed over resumed runs
    num_gaussians: int
    train_psnr: float
    test_psnr: Optional[float]
    test_views: list[int]
    skipped_steps: int
    resumed_from: Optional[int]
    extent: float
    depth_median_abs: Optional[float] = None  # median |expected depth - GT| over alpha > 0.5
    depth_median_rel_extent: Optional[float] = None  # the same divided by ``extent``
    loss_curve: list[tuple[int, float]] = field(default_factory=list)  # (step, loss), subsampled
    step_time_median_s: Optional[float] = None  # wall time per step of this invocation
    step_time_p95_s: Optional[float] = None
    test_psnr_per_view: dict = field(default_factory=dict)  # image name -> dB (held-out views)
    threads: int = 1
    config: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)


# ------------------------------------------------------------------------------------ data
def initial_gaussians(scene: Scene, config: FitConfig, init: Union[None, str, Gaussians]) -> Gaussians:
    if isinstance(init, Gaussians):
        return init.clone().to(config.device)
    g = _initial_gaussians(scene, config, init)
    if config.init_max_scale is not None:
        with torch.no_grad():
            limit = math.log(config.init_max_scale * scene.extent())
            g.set_params(log_scales=g.log_scales.clamp(max=limit))
    return g


def _initial_gaussians(scene: Scene, config: FitConfig, init: Union[None, str]) -> Gaussians:
    kind = init_kind(scene, init)
    train, _ = split_views(scene, config.test_every)
    cameras = [scene.cameras[i] for i in train]

    def image(k: int) -> np.ndarray:  # k indexes ``cameras``
        return scene.image(train[k])

    if kind == "points":
        if scene.points is None or not len(scene.points):
            raise InputError(scene.root, "--init points: the scene has no sparse points (use --init random)")
        points = np.asarray(scene.points, dtype=np.float64)
        colors = scene.point_colors if scene.point_colors is not None else np.full_like(points, 128, np.uint8)
        if config.init_extra_random > 0:
            cells = [uncovered_cells(points, cam) for cam in cameras]
            n_extra = int(round(config.init_extra_random * len(points) * np.mean([c.mean() for c in cells])))
            if n_extra > 0:
                # near/far are unused: the shell sets each point's depth
                extra, extra_colors = random_points_in_frusta(
                    cameras,
                    n_extra,
                    1.0,
                    2.0,
                    seed=config.seed,
                    images=image,
                    cells=cells,
                    shell=background_shell(cameras, points),
                )
                points, colors = np.concatenate([points, extra]), np.concatenate([colors, extra_colors])
        if config.init_extra_seen > 0:
            near, far = (d * scene.extent() for d in config.random_init_depth)
            extra, extra_colors = random_points_seen(
                cameras,
                config.init_extra_seen,
                near,
                far,
                seed=config.seed,
                images=image,
                min_seen=config.random_init_min_seen,
            )
            points, colors = np.concatenate([points, extra]), np.concatenate([colors, extra_colors])
        return init_from_points(points, colors, sh_degree=config.sh_degree, device=config.device)
    if kind == "random":
        ext = scene.extent()
        near, far = (d * ext for d in config.random_init_depth)
        return init_random_in_frusta(
            cameras,
            config.random_init_count,
            near,
            far,
            seed=config.seed,
            sh_degree=config.sh_degree,
            device=config.device,
            images=image,
            shell_fraction=config.random_init_shell,
            min_seen=config.random_init_min_seen,
        )
    raise ValueError(f"unknown init {kind!r}: use 'points', 'random' or a Gaussians model")


class _ViewSampler:
    """Random permutations of the training views, one per epoch (3DGS's viewpoint stack)."""

    def __init__(self, views: list[int], generator: torch.Generator) -> None:
        self.views, self.generator, self.stack = list(views), generator, []

    def next(self) -> int:
        if not self.stack:
            self.stack = [self.views[i] for i in torch.randperm(len(self.views), generator=self.generator).tolist()]
        return self.stack.pop()


# ------------------------------------------------------------------------------------ fitting
def border_color(scene: Scene, views: list[int]) -> tuple[float, float, float]:
    """Per-channel median of the outermost pixel ring of the given views (at most 32 of them,
    evenly spaced): the backdrop's colour when there is one."""
    pick = views[:: max(1, math.ceil(len(views) / 32))]
    rings = []
    for i in pick:
        im = scene.image(i)
        rings += [im[0], im[-1], im[:, 0], im[:, -1]]
    red, green, blue = np.median(np.concatenate(rings), axis=0)  # scene images are [H, W, 3]
    return float(red), float(green), float(blue)


def resolution_factor(config: FitConfig, step: int) -> float:
    """The further downscale of step ``step`` (1-based) under the coarse-to-fine schedule."""
    for until, factor in zip(config.coarse_until, config.coarse_downscale):
        if step <= until * config.steps:
            return float(factor)
    return 1.0


def downsample_image(image: Tensor, height: int, width: int) -> Tensor:  # [H, W, C] -> [height, width, C]
    """Area average (each output pixel the mean of the input pixels it covers)."""
    if image.shape[:2] == (height, width):
        return image
    return F.interpolate(image.permute(2, 0, 1)[None], size=(height, width), mode="area")[0].permute(1, 2, 0)


class Environment(torch.nn.Module):
    """The learned background: RGB = max(SH(ray direction) + 0.5, 0), like a Gaussian's colour,
    seen through every pixel where the Gaussians leave transmittance."""

    def __init__(self, degree: int, color: tuple[float, float, float]) -> None:
        super().__init__()
        from ..render.sh import num_sh_bases

        sh = torch.zeros(num_sh_bases(degree), 3)
        sh[0] = rgb_to_sh(torch.tensor(color, dtype=torch.float32))
        self.degree = degree
        self.sh = torch.nn.Parameter(sh)  # [K, 3]

    def forward(self, camera) -> Tensor:  # [H, W, 3] for one camera's pixel centres
        from ..render.sh import eval_sh

        dirs = torch.as_tensor(camera.ray_directions(), dtype=self.sh.dtype, device=self.sh.device)
        h, w = dirs.shape[:2]
        flat = dirs.reshape(-1, 3)
        return eval_sh(self.sh[None].expand(flat.shape[0], -1, -1), flat, self.degree).reshape(h, w, 3)

    def to_dict(self) -> dict:
        return {
            "kind": "spherical-harmonics",
            "degree": self.degree,
            "convention": "rgb = max(sum_k sh[k] * Y_k(unit ray direction, world) + 0.5, 0), 3DGS's SH basis",
            "sh": self.sh.detach().cpu().tolist(),
        }

    @staticmethod
    def from_dict(d: dict) -> "Environment":
        """The background :meth:`to_dict` wrote (the same float32 coefficients)."""
        from ..render.sh import num_sh_bases

        degree = int(d["degree"])
        sh = torch.tensor(d["sh"], dtype=torch.float32)
        if d.get("kind") != "spherical-harmonics" or tuple(sh.shape) != (num_sh_bases(degree), 3):
            raise ValueError(f"not a spherical-harmonics background of degree {degree}")
        env = Environment(degree, (0.0, 0.0, 0.0))
        with torch.no_grad():
            env.sh.copy_(sh)
        return env.requires_grad_(False)


BACKGROUND_NAME = "background.json"


def read_background(folder: Union[str, Path], device: Union[str, torch.device] = "cpu") -> Optional[Environment]:
    """The learned background a fit saved in ``folder`` (``background.json``, also copied into a
    trained run beside its ``gaussians.ply``); None without one: the fit rendered on black."""
    import json

    path = Path(folder) / BACKGROUND_NAME
    if not path.is_file():
        return None
    try:
        return Environment.from_dict(json.loads(path.read_text())).to(device)
    except (OSError, ValueError, KeyError, TypeError) as e:  # JSONDecodeError is a ValueError
        raise InputError(path, f"unreadable learned background ({e})") from None


def _render(g: Gaussians, camera, config: FitConfig, env: Optional[Environment] = None):
    from ..render import render_rgb

    if env is None:
        return render_rgb(
            g,
            camera,
            sh_degree=g.sh_degree,
            background=torch.tensor(config.background, dtype=torch.float32, device=config.device),
        )
    out = render_rgb(g, camera, sh_degree=g.sh_degree, background=None)
    out.features = out.features + (1.0 - out.alpha) * env(camera)
    return out


def depth_spread_penalty(spread: Tensor) -> Tensor:  # spread [H, W] from _render_with_depth_spread
    """Pixel mean of ``sqrt(spread)`` (smoothed at 0, where the square root's slope is infinite)."""
    return (torch.sqrt(spread + 1e-6) - 1e-3).mean()


def _render_with_depth_spread(
    g: Gaussians, camera, config: FitConfig, extent: float, env: Optional[Environment] = None
):
    """Render colours plus the per-pixel depth spread ``sum_i w_i z_i^2 - (sum_i w_i z_i)^2 /
    alpha`` (z / extent), from one extra rasterized channel. Returns (output, spread [H, W])."""
    from ..render import rasterize, view_colors

    means = g.means
    cam = camera.to_torch(device=means.device, dtype=means.dtype)
    colors = view_colors(g, camera)  # [N, 3]
    z = (means @ cam["viewmat"][2, :3] + cam["viewmat"][2, 3]) / extent  # [N] camera z / extent
    background = (
        None if env is not None else torch.tensor((*config.background, 0.0), dtype=means.dtype, device=means.device)
    )
    out = rasterize(
        means, g.quats, g.scales, g.opacities, torch.cat([colors, (z * z)[:, None]], 1), camera, background=background
    )
    if env is not None:
        out.features = torch.cat([out.features[..., :3] + (1.0 - out.alpha) * env(camera), out.features[..., 3:]], -1)
    second = out.features[..., 3]  # sum w z^2
    mean = out.depth[..., 0] / extent  # sum w z / alpha
    spread = (second - out.alpha[..., 0] * mean * mean).clamp_min(0.0)
    return out, spread


def _checkpoint(
    step: int,
    g: Gaussians,
    adam: GaussianAdam,
    stats: DensifyStats,
    config: FitConfig,
    generator: torch.Generator,
    sampler: _ViewSampler,
    loss_curve: list,
    skipped: int,
    train_time: float,
) -> dict:
    return {
        "format": _CHECKPOINT_FORMAT,
        "step": step,
        "sh_degree": g.sh_degree,
        "params": {k: v.detach().cpu().clone() for k, v in g.params().items()},
        "optimizer": adam.state_dict(),
        "densify": stats.state_dict(),
        "config": config.to_dict(),
        "rng": generator.get_state(),
        "view_stack": list(sampler.stack),
        "loss_curve": list(loss_curve),
        "skipped": skipped,
        "train_time": train_time,
    }


def _state_finite(g: Gaussians, adam: GaussianAdam) -> bool:
    return g.finite() and all(bool(torch.isfinite(t).all()) for d in adam._moments() for t in d.values())


def load_checkpoint(path: Path) -> dict:
    ck = load_torch(path, "checkpoint")
    if not isinstance(ck, dict) or ck.get("format") != _CHECKPOINT_FORMAT:
        raise InputError(path, "not an n2f2 fit-gaussians checkpoint")
    return ck


def saved_config(out_dir: Union[str, Path]) -> Optional[FitConfig]:
    """The config of the checkpoint in ``out_dir``, or None when there is none."""
    path = Path(out_dir) / CHECKPOINT_NAME
    return FitConfig.from_dict(load_checkpoint(path)["config"]) if path.is_file() else None


def fit_gaussians(
    scene: Scene,
    config: FitConfig,
    out_dir: Union[str, Path],
    resume: bool = False,
    init: Union[None, str, Gaussians] = None,  # None: sparse points when the scene has them
    progress: bool = True,
    stop_after: Optional[int] = None,  # end early after this step (checkpointed), for tests/tools
) -> FitReport:
    """Fit Gaussians to ``scene``'s training views; write ``gaussians.ply``, ``fit_report.json``
    and ``checkpoint.pt`` to ``out_dir``. With ``resume`` and a checkpoint in ``out_dir``,
    continue from it (its config is used, except ``steps`` and ``checkpoint_every``).

    On CPU, torch's own operations run on one thread and the compiled render on all of torch's
    (:func:`~n2f2.render.numba_backend.torch_on_one_thread`)."""
    if torch.device(config.device).type != "cpu":
        return _fit_gaussians(scene, config, out_dir, resume, init, progress, stop_after)
    from ..render.numba_backend import torch_on_one_thread

    with torch_on_one_thread():
        return _fit_gaussians(scene, config, out_dir, resume, init, progress, stop_after)


@dataclass
class _Fit:
    """One fit: what it reads (the scene, its training images, the settings) and what its loop
    carries from step to step, most of which a checkpoint saves."""

    scene: Scene
    config: FitConfig
    ck_path: Path
    extent: float
    device: torch.device
    progress: bool
    g: Gaussians
    adam: GaussianAdam
    stats: DensifyStats  # view-space gradients since the last densification
    generator: torch.Generator  # every random draw of the fit
    sampler: _ViewSampler
    env: Optional[Environment]  # the learned background, if any
    env_adam: Optional[torch.optim.Adam]  # its optimiser, created with it
    loss_curve: list  # (step, loss) every log_every steps
    skipped: int  # steps skipped for a non-finite loss, gradient or update
    train_time: float
    targets: dict[int, Tensor] = field(default_factory=dict)  # training view -> image [H, W, 3]
    k: int = 0  # SH coefficients per channel at the start
    t_train: float = 0.0  # when train_time was last brought up to date
    ema: Optional[float] = None  # of the loss, for the progress bar
    bad_run: int = 0  # skipped steps in a row: MAX_BAD_STEPS of them stop the fit
    coarse_targets: dict[tuple[int, float], Tensor] = field(default_factory=dict)  # (view, factor) -> image
    step_times: list[float] = field(default_factory=list)


def _fit_gaussians(
    scene: Scene,
    config: FitConfig,
    out_dir: Union[str, Path],
    resume: bool,
    init: Union[None, str, Gaussians],
    progress: bool,
    stop_after: Optional[int],
) -> FitReport:
    from tqdm.auto import tqdm

    t_start = time.perf_counter()
    out_dir = Path(out_dir)
    ck_path = out_dir / CHECKPOINT_NAME
    extent = scene.extent()
    device = torch.device(config.device)

    ck = load_checkpoint(ck_path) if resume and ck_path.is_file() else None
    if resume and ck is None and progress:
        print(f"fit-gaussians: no checkpoint in {out_dir}, starting from scratch")
    if ck is not None:
        config = replace(
            FitConfig.from_dict(ck["config"]),
            steps=config.steps,
            checkpoint_every=config.checkpoint_every,
            device=config.device,
        )
    train_views, test_views = split_views(scene, config.test_every)
    # Checked now, not after the training: the depth metric's views (optional ground truth).
    gt = scene.ground_truth
    depth_views = [] if gt is None else gt.views_with_depth(test_views or train_views, "the depth error")
    if ck is None and config.background_from_images:
        config = replace(config, background=border_color(scene, train_views), background_from_images=False)

    f, start = _initial_fit(scene, config, init, train_views, ck, ck_path, extent, device, progress)
    f.targets = {i: torch.from_numpy(scene.image(i)).to(device) for i in train_views}
    f.k = f.g.sh.shape[1]
    end = config.steps if stop_after is None else min(config.steps, stop_after)
    bar = tqdm(total=config.steps, initial=start, disable=not progress, desc="fit-gaussians", dynamic_ncols=True)
    f.t_train = time.perf_counter()
    step = start
    for step in range(start + 1, end + 1):
        _fit_step(f, step, bar)
    bar.close()
    if f.step_times and f.bad_run == len(f.step_times):
        raise _fit_stopped(step, f"all {f.bad_run} steps of this run")
    f.train_time += time.perf_counter() - f.t_train
    final = max(step, start)
    _save_fit_checkpoint(f, final)
    return _fit_report(f, final, train_views, test_views, depth_views, out_dir, ck, t_start)


def _initial_fit(
    scene: Scene,
    config: FitConfig,
    init: Union[None, str, Gaussians],
    train_views: list[int],
    ck: Optional[dict],
    ck_path: Path,
    extent: float,
    device: torch.device,
    progress: bool,
) -> tuple[_Fit, int]:
    """(the fit's state, the step it starts after): new Gaussians (``init``), optimiser and
    background seeded with ``config.seed``, or the checkpoint ``ck``'s state."""
    generator = torch.Generator().manual_seed(config.seed)
    sampler = _ViewSampler(train_views, generator)
    adam = GaussianAdam(eps=config.adam_eps)
    if ck is None:
        g = initial_gaussians(scene, config, init)
        if not isinstance(init, Gaussians):
            g.sh_degree = 0  # the SH schedule starts from the DC colour (3DGS)
        start, loss_curve, skipped, train_time = 0, [], 0, 0.0
        stats = DensifyStats.zeros(g.num, device)
    else:
        g = Gaussians(**ck["params"], sh_degree=ck["sh_degree"]).to(device)
        adam.load_state_dict(ck["optimizer"], device)
        stats = DensifyStats(**{k: v.to(device) for k, v in ck["densify"].items()})
        generator.set_state(ck["rng"])
        sampler.stack = list(ck["view_stack"])
        start, loss_curve, skipped, train_time = ck["step"], list(ck["loss_curve"]), ck["skipped"], ck["train_time"]

    env: Optional[Environment] = None
    env_adam: Optional[torch.optim.Adam] = None
    if config.background_sh_degree >= 0:
        env = Environment(config.background_sh_degree, config.background).to(device)
        env_adam = torch.optim.Adam(env.parameters(), lr=config.background_lr, eps=config.adam_eps)
        if ck is not None and "environment" in ck:
            with torch.no_grad():
                env.sh.copy_(ck["environment"]["sh"])
            env_adam.load_state_dict(ck["environment"]["optimizer"])
    fit = _Fit(
        scene=scene,
        config=config,
        ck_path=ck_path,
        extent=extent,
        device=device,
        progress=progress,
        g=g,
        adam=adam,
        stats=stats,
        generator=generator,
        sampler=sampler,
        env=env,
        env_adam=env_adam,
        loss_curve=loss_curve,
        skipped=skipped,
        train_time=train_time,
    )
    return fit, start


def _save_fit_checkpoint(f: _Fit, step: int) -> None:
    """Write the checkpoint of ``step``, unless the state holds a non-finite value (never persist
    a broken state)."""
    if _state_finite(f.g, f.adam) and (f.env is None or bool(torch.isfinite(f.env.sh).all())):
        state = _checkpoint(
            step, f.g, f.adam, f.stats, f.config, f.generator, f.sampler, f.loss_curve, f.skipped, f.train_time
        )
        if f.env is not None:
            assert f.env_adam is not None  # created together with env
            state["environment"] = {"sh": f.env.sh.detach().cpu().clone(), "optimizer": f.env_adam.state_dict()}
        save_torch(f.ck_path, state, keep=True)  # resumable state: kept if the command fails


def _fit_step(f: _Fit, step: int, bar: Any) -> None:
    """Step ``step`` (1-based): render one training view (coarse-to-fine), the photometric loss
    (plus the depth-spread penalty), the update unless something is not finite, the loss curve,
    densification, and a checkpoint every ``checkpoint_every`` steps."""
    t_step = time.perf_counter()
    config, g, env = f.config, f.g, f.env
    if step % config.sh_degree_interval == 0 and g.sh_degree < g.max_sh_degree:
        g.sh_degree += 1
    view = f.sampler.next()
    camera = f.scene.cameras[view]
    target = f.targets[view]
    factor = resolution_factor(config, step)
    if factor != 1.0:
        camera = camera.downscaled(factor)
        if (view, factor) not in f.coarse_targets:
            f.coarse_targets[(view, factor)] = downsample_image(target, camera.height, camera.width)
        target = f.coarse_targets[(view, factor)]
    elif f.coarse_targets:
        f.coarse_targets.clear()  # the schedule has ended
    if config.depth_spread_weight > 0:
        out, spread = _render_with_depth_spread(g, camera, config, f.extent, env)
        image = out.features[..., :3]
    else:
        out, spread = _render(g, camera, config, env), None
        image = out.features  # not clamped: 3DGS trains on the raw composite
    out.means2d.retain_grad()
    loss = photometric_loss(image, target, config.lambda_dssim)
    if spread is not None:
        loss = loss + config.depth_spread_weight * depth_spread_penalty(spread)
    g.zero_grad(set_to_none=True)
    if env is not None:
        assert f.env_adam is not None  # created together with env
        f.env_adam.zero_grad(set_to_none=True)
    loss.backward()
    # Parameter gradients are checked by the optimiser; it refuses non-finite steps.
    grads_ok = bool(torch.isfinite(loss)) and (out.means2d.grad is None or bool(torch.isfinite(out.means2d.grad).all()))
    env_ok = env is None or (env.sh.grad is not None and bool(torch.isfinite(env.sh.grad).all()))
    ok = grads_ok and env_ok and f.adam.step(g.params(), learning_rates(config, step, f.extent, f.k, f.device))
    if ok and env is not None:
        assert f.env_adam is not None  # created together with env
        f.env_adam.step()
    g.zero_grad(set_to_none=True)
    if not ok:
        f.skipped += 1
        f.bad_run += 1
        if f.bad_run >= MAX_BAD_STEPS:
            bar.close()
            raise _fit_stopped(step, f"the last {f.bad_run} steps")
    else:
        f.bad_run = 0
        if step < config.densify_until and out.means2d.grad is not None:
            f.stats.add(out.means2d.grad, out.radii, camera.width, camera.height)
        lv = float(loss.detach())
        f.ema = lv if f.ema is None else 0.9 * f.ema + 0.1 * lv
        if step % config.log_every == 0 or step == 1:
            f.loss_curve.append((step, lv))
        if step % config.log_every == 0 and f.progress:
            bar.set_postfix(
                loss=f"{f.ema:.4f}", psnr=f"{psnr(image.detach().clamp(0, 1), target):.2f}", G=g.num, refresh=False
            )
    _densify(f, step)
    f.step_times.append(time.perf_counter() - t_step)
    bar.update(1)
    if config.checkpoint_every and step % config.checkpoint_every == 0:
        f.train_time += time.perf_counter() - f.t_train
        f.t_train = time.perf_counter()
        _save_fit_checkpoint(f, step)


def _densify(f: _Fit, step: int) -> None:
    """Adaptive density control of step ``step``: clone, split and prune every
    ``densify_every`` steps in the densification window, and the periodic opacity reset."""
    config = f.config
    if step < config.densify_until:
        if step > config.densify_from and step % config.densify_every == 0:
            densify_and_prune(
                f.g,
                f.adam,
                f.stats,
                config,
                f.extent,
                prune_big=0 < config.opacity_reset_every < step,
                generator=f.generator,
            )
            f.stats = DensifyStats.zeros(f.g.num, f.device)
        if config.opacity_reset_every and step % config.opacity_reset_every == 0:
            reset_opacity(f.g, f.adam)


def _fit_report(
    f: _Fit,
    final: int,
    train_views: list[int],
    test_views: list[int],
    depth_views: list[int],
    out_dir: Path,
    ck: Optional[dict],
    t_start: float,
) -> FitReport:
    """Evaluate the fitted Gaussians and write ``gaussians.ply``, the background (if learned)
    and ``fit_report.json``; returns the report."""
    from ..render.numba_backend import kernel_threads

    config = f.config
    report = evaluate(
        f.g,
        f.scene,
        train_views,
        test_views,
        config,
        f.extent,
        renders_dir=out_dir / TEST_RENDERS_DIR,
        env=f.env,
        depth_views=depth_views,
    )
    report.update(
        steps=final,
        train_time_s=f.train_time,
        skipped_steps=f.skipped,
        resumed_from=None if ck is None else int(ck["step"]),
        loss_curve=_subsample(f.loss_curve, 200),
        config=config.to_dict(),
        threads=kernel_threads(),  # the render's; torch's own operations run on one (above)
    )
    if f.step_times:
        report.update(
            step_time_median_s=float(np.median(f.step_times)),
            step_time_p95_s=float(np.percentile(f.step_times, 95)),
        )
    write_ply(out_dir / PLY_NAME, f.g)  # refuses non-finite values (cannot happen: steps are guarded)
    if f.env is not None:
        write_json(out_dir / BACKGROUND_NAME, f.env.to_dict())
    report["wall_time_s"] = time.perf_counter() - t_start
    result = FitReport(**report)
    write_json(out_dir / REPORT_NAME, result.to_dict())
    return result


def _fit_stopped(step: int, which: str) -> NonFiniteError:
    return NonFiniteError(
        None,
        f"fit stopped at step {step}: {which} had a NaN or infinite loss or gradient and "
        "were skipped (nothing non-finite was saved); check the images and the options "
        "(--depth-spread)",
    )


def _subsample(curve: list, n: int) -> list:
    if len(curve) <= n:
        return [tuple(c) for c in curve]
    idx = np.linspace(0, len(curve) - 1, n).round().astype(int)
    return [tuple(curve[i]) for i in idx]


@torch.no_grad()
def evaluate(
    g: Gaussians,
    scene: Scene,
    train_views: list[int],
    test_views: list[int],
    config: FitConfig,
    extent: float,
    renders_dir: Optional[Path] = None,
    env: Optional[Environment] = None,
    depth_views: Sequence[int] = (),
) -> dict:
    """Mean PSNR over train and test views; with ground truth, the median absolute error of the
    rendered expected depth over pixels with alpha > 0.5 of ``depth_views`` (the fit passes the
    test views, or the train views if none, whose depth files exist).
    With ``renders_dir``, each held-out view is written there as ``<stem>.png`` (render on the
    left, photo on the right) and ``<stem>.npy`` (the render, float32 [H, W, 3])."""
    from ..io import write_npy, write_png

    device = torch.device(config.device)

    def view_psnr(i: int):
        out = _render(g, scene.cameras[i], config, env)
        return psnr(out.features.clamp(0, 1), torch.from_numpy(scene.image(i)).to(device)), out

    train_psnr = float(np.mean([view_psnr(i)[0] for i in train_views]))
    test_psnr, errors = None, []
    gt = scene.ground_truth
    outs = {}
    per_view = {}
    if test_views:
        vals = []
        for i in test_views:
            v, outs[i] = view_psnr(i)
            vals.append(v)
            per_view[scene.image_names[i]] = v
            if renders_dir is not None:
                render = outs[i].features.clamp(0, 1).cpu().numpy().astype(np.float32)
                stem = Path(scene.image_names[i]).stem
                write_npy(renders_dir / f"{stem}.npy", render)
                pair = np.concatenate([render, scene.image(i)], axis=1)
                write_png(renders_dir / f"{stem}.png", (pair * 255.0 + 0.5).astype(np.uint8))
        test_psnr = float(np.mean(vals))
    depth_abs = depth_rel = None
    if gt is not None:
        for i in depth_views:
            out = outs.get(i) or _render(g, scene.cameras[i], config, env)
            err = _depth_errors(gt.depth(i), out.depth[..., 0].cpu().numpy(), out.alpha[..., 0].cpu().numpy())
            errors.append(err)
        errors = np.concatenate(errors) if errors else np.zeros(0)
        if len(errors):
            depth_abs = float(np.median(errors))
            depth_rel = depth_abs / extent
    return {
        "num_gaussians": g.num,
        "train_psnr": train_psnr,
        "test_psnr": test_psnr,
        "test_views": list(test_views),
        "test_psnr_per_view": per_view,
        "extent": extent,
        "depth_median_abs": depth_abs,
        "depth_median_rel_extent": depth_rel,
    }


def _depth_errors(gt: np.ndarray, depth: np.ndarray, alpha: np.ndarray) -> np.ndarray:  # [Hg, Wg], [H, W], [H, W]
    """|depth - gt| at pixels with alpha > 0.5 and a valid GT depth; GT (full resolution) is
    resized to the render size with nearest-neighbour sampling at the render's pixel centres."""
    h, w = depth.shape
    if gt.shape != (h, w):
        rows = np.minimum(((np.arange(h) + 0.5) * gt.shape[0] / h).astype(int), gt.shape[0] - 1)
        cols = np.minimum(((np.arange(w) + 0.5) * gt.shape[1] / w).astype(int), gt.shape[1] - 1)
        gt = gt[rows][:, cols]
    valid = (alpha > 0.5) & np.isfinite(gt) & (gt > 0)
    return np.abs(depth[valid] - gt[valid])
