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

import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import ClassVar, Optional, Union

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..config import ConfigDict, option
from ..data.scene import Scene
from ..errors import InputError
from ..io import load_torch, save_torch, write_json
from ..validate import MAX_BAD_STEPS, NonFiniteError, nonneg_float, nonneg_int, positive_int
from .init import (
    background_shell,
    init_from_points,
    init_random_in_frusta,
    random_points_in_frusta,
    random_points_seen,
    uncovered_cells,
)
from .model import Gaussians, inverse_sigmoid, quat_to_rotmat, rgb_to_sh
from .ply import write_ply

CHECKPOINT_NAME = "checkpoint.pt"
PLY_NAME = "gaussians.ply"
REPORT_NAME = "fit_report.json"
TEST_RENDERS_DIR = "test_views"  # held-out renders beside their photos (PNG + float32 .npy)
_CHECKPOINT_FORMAT = "n2f2-gaussians-checkpoint-v1"


# ------------------------------------------------------------------------------------ config
@dataclass
class FitConfig(ConfigDict):
    """Hyper-parameters of :func:`fit_gaussians`. Defaults are the 3DGS paper's
    (``arguments/__init__.py`` of the reference code); see :meth:`cpu` and :meth:`paper`.

    Step counters are 1-based as in 3DGS: an event "every n steps" happens after step n, 2n..."""

    PRESETS: ClassVar[tuple[str, ...]] = ("cpu", "paper")  # see the static methods of those names

    # Fields declared with option() are flags of `n2f2 fit-gaussians`; their help lists each
    # preset's value.
    steps: int = option(
        30_000,
        help="optimisation steps of the Gaussian fit; the cpu preset sizes its count to the scene (shown: the "
        "demo scene's) and keeps its schedule's fractions of a count given here",
        type=positive_int,
    )
    sh_degree: int = 3  # maximum SH degree of the model
    sh_degree_interval: int = 1000  # raise the active SH degree by one every this many steps
    lambda_dssim: float = 0.2
    # Weight of the depth-spread regulariser: the pixel mean of sqrt(sum_i w_i (z_i - zbar)^2),
    # z in units of the extent, i.e. the spread of the depths blended into a pixel (times
    # sqrt(alpha)). It pulls the Gaussians along a ray onto one depth, like Mip-NeRF 360's
    # distortion loss (see FitConfig.cpu for what it does on the demo scene). The square root
    # keeps pixels on depth edges (table rim against the far floor) from dominating; the
    # squared form cost 2-3x more PSNR for the same depth gain. 0: off, as in 3DGS.
    depth_spread_weight: float = option(
        0.0,
        help="weight of the depth-spread regulariser, which pulls the Gaussians a ray meets onto one depth; "
        "0 = off, as 3DGS",
        type=nonneg_float,
        flag="depth-spread",
        metavar="W",
    )
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)  # colour behind the Gaussians
    # Replace ``background`` at the start of a fit by the median colour of the training views'
    # border pixels (recorded in the checkpoint and report). A plain backdrop then needs no
    # Gaussians: painting it with them on a black background filled the held-out views of a
    # real object capture with backdrop-coloured floaters (17.5 vs 21.6 dB after 1000 steps).
    background_from_images: bool = False
    # Learn the background as a colour over ray directions (spherical harmonics of this degree,
    # started at ``background``), an environment behind every Gaussian: a real backdrop shades
    # smoothly (light falloff, shadows) where a constant leaves most of a capture's error.
    # Saved as background.json beside the PLY. -1: the constant ``background``, as 3DGS.
    background_sh_degree: int = -1
    background_lr: float = 0.005

    # Adam learning rates. Positions are scaled by the scene extent and decay exponentially
    # from means_lr_init to means_lr_final over means_lr_max_steps.
    means_lr_init: float = 1.6e-4
    means_lr_final: float = 1.6e-6
    means_lr_max_steps: int = 30_000
    sh_dc_lr: float = 2.5e-3
    sh_rest_lr: float = 2.5e-3 / 20.0
    opacity_lr: float = 0.05
    scaling_lr: float = 5e-3
    rotation_lr: float = 1e-3
    adam_eps: float = 1e-15

    # Adaptive density control.
    densify_from: int = 500
    densify_until: int = 15_000
    densify_every: int = 100
    densify_grad_threshold: float = 2e-4  # on the NDC-space positional gradient, as 3DGS
    percent_dense: float = 0.01  # clone below / split above this fraction of the extent
    opacity_reset_every: int = 3000  # 0: never (and then large Gaussians are never pruned)
    prune_opacity: float = 0.005
    prune_world_size: float = 0.1  # prune Gaussians larger than this x extent (after 1st reset)
    max_gaussians: Optional[int] = option(
        None,
        help="cap on the Gaussian count, densification keeping the largest gradients; the cpu preset sizes "
        "it to the views' pixels (shown: the demo scene's)",
        type=positive_int,
        metavar="N",
    )
    # Also split Gaussians whose screen radius exceeded this fraction of the image size since the
    # last densification (gsplat's grow_scale2d); None: off, as in 3DGS.
    split_screen_size: Optional[float] = None

    # Initialisation when the scene has no sparse points (random inside the frusta).
    random_init_count: int = 100_000
    random_init_depth: tuple[float, float] = (0.2, 1.6)  # z-depth range, x extent
    # Largest initial scale, x extent. k-NN distances of sparse or random points can be huge
    # (far walls with few points), and one such Gaussian near a camera covers the whole screen
    # and makes a step many times slower. None: no clamp, as 3DGS.
    init_max_scale: Optional[float] = None
    # With sparse points, also start random Gaussians where they miss: plain walls and backdrops
    # get no SfM points, and densification only grows Gaussians near existing ones. This many
    # per point, times the fraction of the training views' grid cells (16 along the longer side)
    # that no point projects into, drawn through random pixels of those cells (coloured by
    # them) onto a sphere behind every camera (init.background_shell). Generated scenes, whose
    # points cover every surface, get almost none. 0: points only, as 3DGS.
    init_extra_random: float = 0.0
    # With sparse points, also start this many random Gaussians inside the views'
    # overlap (drawn as for a random initialisation: ``random_init_depth``,
    # ``random_init_min_seen``, pixel colours): SfM triangulates no point on textureless
    # surfaces near the object (a mat, a tabletop), and nothing else would grow there. 0: points only.
    init_extra_seen: int = 0
    # Without sparse points: the fraction of the random Gaussians put on that sphere, and the
    # fraction of the training views each of the others must be seen in (0: anywhere in a frustum).
    random_init_shell: float = 0.0
    random_init_min_seen: float = 0.0

    # Coarse to fine: up to step ``coarse_until[i] * steps`` the views are rendered and compared
    # at a further ``coarse_downscale[i]`` (images area-averaged). A step's cost scales with its
    # pixels, and the early model is blurry anyway. Empty: full resolution throughout, as 3DGS.
    coarse_until: tuple[float, ...] = ()
    coarse_downscale: tuple[float, ...] = ()
    # Prune Gaussians whose screen radius exceeded this fraction of the image size since the
    # last densification (gsplat's prune_scale2d), bounding the screen area any one can cover.
    # None: off, as in 3DGS before its first opacity reset.
    prune_screen_size: Optional[float] = None

    # Evaluation and bookkeeping.
    test_every: int = 8  # hold out every n-th view when scene.json lists no test views; 0: none
    checkpoint_every: int = option(
        1000, help="write a checkpoint every N steps; 0: only at the end", type=nonneg_int, metavar="N"
    )
    seed: int = 0
    device: str = "cpu"
    log_every: int = 10  # loss-curve sampling and progress-bar refresh

    @staticmethod
    def paper() -> "FitConfig":
        """The 30k-step schedule of the 3DGS paper (for GPU users)."""
        return FitConfig()

    def sized_for(
        self, scene: Scene, steps: Optional[int] = None, init: Union[None, str, Gaussians] = None
    ) -> "FitConfig":
        """This schedule with its scene-dependent constants derived from ``scene`` (the cpu
        preset's rule; the constants above give the demo scene's 1500 steps and 12k cap):

        * Gaussian cap: ``GAUSSIANS_PER_PIXEL`` per pixel of a (median) view, the detail an
          image can show;
        * steps: ``EPOCHS`` passes over the training views, within [MIN_STEPS, MAX_STEPS];
          the densification window, SH schedule and position-rate decay keep their fractions
          of the run (also when ``steps`` is given);
        * views larger than ``COARSE_PIXELS`` are fitted at about that many pixels for the
          first ``COARSE_FRACTION`` of the steps (a step's cost scales with its pixels);
        * the background is learned only for a backdrop without sparse points
          (``BACKDROP_UNCOVERED``); otherwise it is black, as 3DGS;
        * a random initialisation (``init`` as :func:`fit_gaussians` takes it: ``"random"``, or
          ``None`` on a scene without sparse points) resets opacities every
          ``RANDOM_INIT_RESET_FRACTION`` of the steps, as 3DGS does on every scene: random
          Gaussians that only some training views constrain become floaters in front of the
          others, and only a reset clears them;
        * sparse points that leave a backdrop uncovered get ``BACKDROP_EXTRA_SEEN`` x
          ``random_init_count`` random Gaussians where the views overlap, and the same resets
          (points alone, on generated scenes, do better without resets; see :meth:`cpu`)."""
        train, _ = split_views(scene, self.test_every)
        cams = [scene.cameras[i] for i in train]
        if _has_points(scene):
            points = scene.points
            assert points is not None  # _has_points checked it
            uncovered = float(np.mean([uncovered_cells(points, c).mean() for c in cams]))
        else:
            uncovered = 1.0
        backdrop = uncovered > BACKDROP_UNCOVERED
        pixels = float(np.median([c.width * c.height for c in scene.cameras]))
        if steps is None:
            steps = int(np.clip(round(EPOCHS * len(train), -2), MIN_STEPS, MAX_STEPS))
        ref = FitConfig.cpu()  # the fractions of the 1500-step schedule
        frac = steps / ref.steps
        kind = init_kind(scene, init)
        # Random Gaussians (all of them, or beside points that miss a backdrop) need resets.
        extra_seen = round(BACKDROP_EXTRA_SEEN * self.random_init_count) if backdrop and kind == "points" else 0
        random_part = kind == "random" or extra_seen > 0
        reset = int(round(RANDOM_INIT_RESET_FRACTION * steps, -2)) if random_part else self.opacity_reset_every
        coarse = math.sqrt(pixels / COARSE_PIXELS)
        return replace(
            self,
            steps=steps,
            max_gaussians=max(2000, int(round(GAUSSIANS_PER_PIXEL * pixels))),
            means_lr_max_steps=steps,
            sh_degree_interval=max(1, round(ref.sh_degree_interval * frac)),
            densify_from=round(ref.densify_from * frac),
            densify_until=round(ref.densify_until * frac),
            coarse_until=(COARSE_FRACTION,) if coarse > 1.25 else (),
            coarse_downscale=(coarse,) if coarse > 1.25 else (),
            background_from_images=self.background_from_images and backdrop,
            background_sh_degree=self.background_sh_degree if backdrop else -1,
            opacity_reset_every=reset,
            init_extra_seen=extra_seen or self.init_extra_seen,
        )

    @staticmethod
    def cpu() -> "FitConfig":
        """A short schedule for small scenes on a CPU (the built-in demo scene in under 1.5
        minutes on 2 cores): fewer steps, earlier and capped densification, faster SH schedule;
        the decay of the position learning rate is compressed to the shorter run.

        Two 3DGS rules are off because a 1500-step run has no time to recover from them: no
        opacity reset (3DGS resets every 3000 steps and trains 27k more), and so, as in 3DGS
        before its first reset, no pruning of Gaussians larger than 0.1 x extent (the far floor
        and wall need large ones).

        One rule is added: the depth-spread regulariser (``depth_spread_weight=1.0``), because
        segment lifting needs the rendered depth; 1.0 keeps the demo's held-out depth error under
        2 % of the extent and its PSNR over 27 dB. It fixes the surfaces seen with parallax; the
        far floor and walls, seen by the ring of cameras at low parallax, stay off with or
        without it.

        For scenes it was not tuned on (real photos, captures without sparse points): initial
        scales at most 0.1 x extent (the size 3DGS prunes above), and the background learned
        over ray directions from the views' border colour (``background_sh_degree=2``) where the
        sparse points leave a backdrop uncovered. ``sized_for`` then fits steps, cap, schedule
        and initialisation to the scene. The measurements behind each rule are in
        docs/measurements.md ("The cpu fit preset")."""
        return FitConfig(
            steps=1500,
            depth_spread_weight=1.0,
            background_from_images=True,
            background_sh_degree=2,
            random_init_min_seen=0.5,
            init_max_scale=0.1,
            sh_degree_interval=400,
            means_lr_max_steps=1500,
            densify_from=200,
            densify_until=1100,
            densify_every=100,
            opacity_reset_every=0,
            max_gaussians=12_000,
            random_init_count=5000,
            checkpoint_every=500,
        )


# How the cpu preset sizes itself to a scene (FitConfig.sized_for).
GAUSSIANS_PER_PIXEL = 0.625  # Gaussian cap per pixel of one view (160x120 -> 12k)
EPOCHS = 43.0  # passes over the training views (35 views -> 1500 steps; rounded to 100s)
MIN_STEPS, MAX_STEPS = 1000, 2000  # the upper bound keeps a 70-view, 370x250 capture near 10 min on 2 cores
COARSE_PIXELS = 25_000  # views larger than this start coarse, at about this many pixels
COARSE_FRACTION = 0.5  # ... for this fraction of the steps
# Learn the background (border colour, then SH over directions) only when the sparse points
# leave more than this fraction of the training views' grid cells empty, or there are none:
# a backdrop SfM could not triangulate. The generated layouts' points leave 1-3 % empty (their
# walls are surfaces; a learned background cost the tabletop 1 dB), real object captures ~70 %.
BACKDROP_UNCOVERED = 0.1
# Opacity reset period of a random initialisation, as a fraction of the steps: twice inside the
# densification window (which ends at 73 % of the run), the second leaving 30 % of the run to
# recover (3DGS's last reset, at 12k of 30k steps, leaves 60 %).
RANDOM_INIT_RESET_FRACTION = 0.35
# Sparse points that leave a backdrop uncovered (a real object capture: SfM triangulates nothing
# on the plain mat or table around the object) are joined by this many times
# ``random_init_count`` random Gaussians inside the views' overlap (``init_extra_seen``), and the
# fit then resets opacities as a random initialisation does (docs/measurements.md, "Sparse
# points and random Gaussians").
BACKDROP_EXTRA_SEEN = 2.0


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


# ------------------------------------------------------------------------------------ losses
def _gaussian_1d(size: int, sigma: float, device, dtype) -> Tensor:  # [size], sums to 1
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim(
    img1: Tensor,  # [H, W, C]
    img2: Tensor,  # [H, W, C]
    window_size: int = 11,
    sigma: float = 1.5,
) -> Tensor:  # [] mean SSIM
    """Mean SSIM with an 11x11 Gaussian window (sigma 1.5), zero padding, as 3DGS's ``ssim``.

    The window is separable, so it is applied as a 1x11 then an 11x1 pass (with zero padding
    this is the same sum as the 2D window), to the five maps at once: on a CPU the 2D grouped
    convolution cost ~10x more and was a quarter of a fitting step at 370x250 pixels."""
    c = img1.shape[-1]
    a = img1.permute(2, 0, 1)
    b = img2.permute(2, 0, 1)
    maps = torch.cat([a, b, a * a, b * b, a * b])[None]  # [1, 5C, H, W]
    g = _gaussian_1d(window_size, sigma, a.device, a.dtype)
    pad = window_size // 2
    k = 5 * c
    maps = F.conv2d(maps, g.view(1, 1, 1, -1).expand(k, 1, 1, window_size), padding=(0, pad), groups=k)
    maps = F.conv2d(maps, g.view(1, 1, -1, 1).expand(k, 1, window_size, 1), padding=(pad, 0), groups=k)
    mu1, mu2, e11, e22, e12 = maps[0].split(c)
    mu1_sq, mu2_sq, mu12 = mu1 * mu1, mu2 * mu2, mu1 * mu2
    s1, s2, s12 = e11 - mu1_sq, e22 - mu2_sq, e12 - mu12
    c1, c2 = 0.01**2, 0.03**2
    m = ((2 * mu12 + c1) * (2 * s12 + c2)) / ((mu1_sq + mu2_sq + c1) * (s1 + s2 + c2))
    return m.mean()


def psnr(img1: Tensor, img2: Tensor) -> float:  # [H, W, C] each, values in [0, 1]
    mse = float(((img1 - img2) ** 2).mean())
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def photometric_loss(render: Tensor, target: Tensor, lambda_dssim: float) -> Tensor:  # [H, W, 3] each
    """3DGS's ``(1 - lambda) L1 + lambda (1 - SSIM)``."""
    l1 = (render - target).abs().mean()
    return (1.0 - lambda_dssim) * l1 + lambda_dssim * (1.0 - ssim(render, target))


# ------------------------------------------------------------------------------------ optimiser
class GaussianAdam:
    """Adam over the named per-Gaussian parameters, with state kept as plain row-aligned tensors
    so densification can index, extend and reset it (as 3DGS edits ``optimizer.state``).

    Learning rates may be tensors broadcastable to the parameter (the SH tensor uses one rate
    for the DC coefficient and one for the rest). Matches ``torch.optim.Adam`` (no weight decay).
    A step is taken only when it keeps every value finite."""

    def __init__(self, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-15) -> None:
        self.betas = betas
        self.eps = eps
        self.exp_avg: dict[str, Tensor] = {}
        self.exp_avg_sq: dict[str, Tensor] = {}
        self.step_count: dict[str, int] = {}

    @torch.no_grad()
    def step(self, params: dict[str, Tensor], lrs: dict[str, Union[float, Tensor]]) -> bool:
        """One Adam step for every parameter that has a gradient. Returns False, changing
        nothing, when a gradient is not finite or so large that its square overflows (the only
        ways a step from a finite state can produce a non-finite one)."""
        b1, b2 = self.betas
        live = {name: p for name, p in params.items() if p.grad is not None}
        limit = math.sqrt(torch.finfo(torch.float32).max) / 16.0
        for p in live.values():
            grad = p.grad
            assert grad is not None  # live holds only parameters with a gradient
            if not bool(torch.isfinite(grad).all()) or bool((grad.abs() > limit).any()):
                return False
        for name, p in live.items():
            g = p.grad
            assert g is not None  # as above
            if name not in self.exp_avg:
                self.exp_avg[name], self.exp_avg_sq[name] = torch.zeros_like(p), torch.zeros_like(p)
            m, v = self.exp_avg[name], self.exp_avg_sq[name]
            t = self.step_count.get(name, 0) + 1
            self.step_count[name] = t
            m.mul_(b1).add_(g, alpha=1 - b1)
            v.mul_(b2).addcmul_(g, g, value=1 - b2)
            bc1, bc2 = 1 - b1**t, 1 - b2**t
            # torch.optim.Adam: p -= lr / bc1 * m / (sqrt(v) / sqrt(bc2) + eps)
            update = m / v.sqrt().div_(math.sqrt(bc2)).add_(self.eps)
            lr = lrs[name]
            if isinstance(lr, Tensor):
                p.sub_(update.mul_(lr / bc1))
            else:
                p.sub_(update, alpha=lr / bc1)
        return True

    def _moments(self) -> list[dict[str, Tensor]]:
        return [self.exp_avg, self.exp_avg_sq]

    def index_rows(self, rows: Tensor) -> None:  # [M] long or [N] bool
        """Keep (or gather) rows of every state tensor, as the parameters were."""
        for d in self._moments():
            for name in d:
                d[name] = d[name][rows]

    def append_zero_rows(self, n: int) -> None:
        """New Gaussians start with zero moments (3DGS ``cat_tensors_to_optimizer``)."""
        for d in self._moments():
            for name, t in d.items():
                d[name] = torch.cat([t, t.new_zeros((n,) + tuple(t.shape[1:]))])

    def reset(self, name: str) -> None:
        for d in self._moments():
            if name in d:
                d[name] = torch.zeros_like(d[name])

    def state_dict(self) -> dict:
        return {
            "exp_avg": dict(self.exp_avg),
            "exp_avg_sq": dict(self.exp_avg_sq),
            "step_count": dict(self.step_count),
            "betas": self.betas,
            "eps": self.eps,
        }

    def load_state_dict(self, s: dict, device) -> None:
        self.exp_avg = {k: v.to(device) for k, v in s["exp_avg"].items()}
        self.exp_avg_sq = {k: v.to(device) for k, v in s["exp_avg_sq"].items()}
        self.step_count = dict(s["step_count"])
        self.betas, self.eps = tuple(s["betas"]), float(s["eps"])


def means_lr(config: FitConfig, step: int, extent: float) -> float:
    """3DGS ``get_expon_lr_func`` (no delay): log-linear from init to final, times the extent."""
    t = min(max(step / max(config.means_lr_max_steps, 1), 0.0), 1.0)
    return extent * math.exp((1 - t) * math.log(config.means_lr_init) + t * math.log(config.means_lr_final))


def learning_rates(config: FitConfig, step: int, extent: float, k: int, device) -> dict[str, Union[float, Tensor]]:
    sh_lr = torch.full((1, k, 1), config.sh_rest_lr, device=device)
    sh_lr[:, 0] = config.sh_dc_lr
    return {
        "means": means_lr(config, step, extent),
        "quats": config.rotation_lr,
        "log_scales": config.scaling_lr,
        "opacity_logits": config.opacity_lr,
        "sh": sh_lr,
    }


# ------------------------------------------------------------------------------------ densification
@dataclass
class DensifyStats:
    """Per-Gaussian statistics accumulated between densifications (3DGS
    ``xyz_gradient_accum``, ``denom``, ``max_radii2D``)."""

    grad_accum: Tensor  # [N] sum of ||d loss / d NDC mean||
    count: Tensor  # [N] views in which the Gaussian was visible
    max_radii: Tensor  # [N] largest screen radius seen, as a fraction of max(width, height)

    @staticmethod
    def zeros(n: int, device) -> "DensifyStats":
        return DensifyStats(torch.zeros(n, device=device), torch.zeros(n, device=device), torch.zeros(n, device=device))

    @torch.no_grad()
    def add(self, means2d_grad: Tensor, radii: Tensor, width: int, height: int) -> None:  # [N, 2], [N]
        visible = radii > 0
        # Pixel-space gradient -> NDC-space (pixel = ((ndc + 1) W - 1) / 2), the space in
        # which 3DGS's threshold of 2e-4 is defined.
        g = means2d_grad[visible] * torch.tensor([width / 2.0, height / 2.0], device=means2d_grad.device)
        self.grad_accum[visible] += g.norm(dim=-1)
        self.count[visible] += 1
        self.max_radii[visible] = torch.maximum(self.max_radii[visible], radii[visible].float() / max(width, height))

    def state_dict(self) -> dict:
        return asdict(self)


@torch.no_grad()
def densify_and_prune(
    g: Gaussians,
    adam: GaussianAdam,
    stats: DensifyStats,
    config: FitConfig,
    extent: float,
    prune_big: bool,  # also prune Gaussians larger than prune_world_size x extent
    generator: torch.Generator,  # CPU generator for the split samples
) -> dict[str, int]:
    """Clone small and split large Gaussians whose mean NDC gradient exceeds the threshold, then
    prune transparent (and, after the first opacity reset, huge) ones; rebuild the optimiser
    state to match (zeros for new rows). Returns counts of what happened."""
    n = g.num
    grads = stats.grad_accum / stats.count.clamp_min(1)
    grads[stats.count == 0] = 0.0
    candidates = grads >= config.densify_grad_threshold
    # gsplat's ``grow_scale2d``: also split whatever covers too much of the screen, whatever its
    # gradient (ranked after every gradient candidate when the cap bites).
    screen_big = (
        (stats.max_radii > config.split_screen_size) if config.split_screen_size else torch.zeros_like(candidates)
    )
    priority = torch.where(candidates, grads, torch.where(screen_big, torch.zeros_like(grads), -torch.ones_like(grads)))
    candidates = candidates | screen_big
    if config.max_gaussians is not None:
        budget = max(0, config.max_gaussians - n)
        if int(candidates.sum()) > budget:
            # Keep the highest priority: each clone or split adds exactly one Gaussian.
            order = torch.argsort(priority, descending=True, stable=True)
            keep = torch.zeros_like(candidates)
            keep[order[:budget]] = True
            candidates &= keep
    big = (g.scales.max(dim=1).values > config.percent_dense * extent) | screen_big
    clone = candidates & ~big
    split = candidates & big

    p = g.params()
    new = {name: [t, t[clone]] for name, t in p.items()}
    n_split = int(split.sum())
    if n_split:
        scales = g.scales[split].repeat(2, 1)  # [2S, 3]
        samples = torch.normal(torch.zeros_like(scales, device="cpu"), scales.cpu(), generator=generator)
        rots = quat_to_rotmat(p["quats"][split]).repeat(2, 1, 1)
        new["means"].append(
            torch.bmm(rots, samples.to(scales.device)[..., None])[..., 0] + p["means"][split].repeat(2, 1)
        )
        new["log_scales"].append(torch.log(scales / (0.8 * 2)))
        for name in ("quats", "opacity_logits", "sh"):
            t = p[name][split]
            new[name].append(t.repeat((2,) + (1,) * (t.ndim - 1)))
    merged = {name: torch.cat(parts) for name, parts in new.items()}
    n_added = merged["means"].shape[0] - n
    adam.append_zero_rows(n_added)

    prune = torch.cat([split, torch.zeros(n_added, dtype=torch.bool, device=split.device)])
    prune |= torch.sigmoid(merged["opacity_logits"]) < config.prune_opacity
    if config.prune_screen_size:
        screen = torch.cat([stats.max_radii, stats.max_radii[clone], stats.max_radii[split].repeat(2) / 1.6])
        prune |= screen > config.prune_screen_size
    if prune_big:
        prune |= torch.exp(merged["log_scales"]).max(dim=1).values > config.prune_world_size * extent
    keep = ~prune
    g.set_params(**{name: t[keep] for name, t in merged.items()})
    adam.index_rows(keep)
    return {"cloned": int(clone.sum()), "split": n_split, "pruned": int(prune.sum()) - n_split}


@torch.no_grad()
def reset_opacity(g: Gaussians, adam: GaussianAdam, value: float = 0.01) -> None:
    """Clamp every opacity to at most ``value`` and forget its Adam moments (3DGS)."""
    g.set_params(opacity_logits=inverse_sigmoid(torch.clamp(g.opacities, max=value)))
    adam.reset("opacity_logits")


# ------------------------------------------------------------------------------------ data
def split_views(scene: Scene, test_every: int) -> tuple[list[int], list[int]]:
    """(train, test) view indices: scene.json's ``test_views`` when present, else every
    ``test_every``-th view (3DGS ``llffhold``: indices 0, 8, 16, ...); no test views if 0."""
    n = len(scene)
    test: list[int] = []
    meta = Path(scene.root) / "scene.json"
    listed = None
    if meta.is_file():
        try:
            listed = json.loads(meta.read_text()).get("test_views")
        except (json.JSONDecodeError, AttributeError):
            raise InputError(meta, "not a valid JSON object") from None
    if listed is not None:
        if not all(isinstance(i, int) and 0 <= i < n for i in listed):
            raise InputError(meta, f"test_views must be view indices in [0, {n})")
        test = sorted(set(listed))
    elif test_every > 0 and n > 1:
        test = list(range(0, n, test_every))
    train = [i for i in range(n) if i not in set(test)]
    if not train:
        raise InputError(scene.root, "no training views left after holding out the test views")
    return train, test


def initial_gaussians(scene: Scene, config: FitConfig, init: Union[None, str, Gaussians]) -> Gaussians:
    if isinstance(init, Gaussians):
        return init.clone().to(config.device)
    g = _initial_gaussians(scene, config, init)
    if config.init_max_scale is not None:
        with torch.no_grad():
            limit = math.log(config.init_max_scale * scene.extent())
            g.set_params(log_scales=g.log_scales.clamp(max=limit))
    return g


def _has_points(scene: Scene) -> bool:
    return scene.points is not None and len(scene.points) > 0


def init_kind(scene: Scene, init: Union[None, str, Gaussians]) -> str:
    """What :func:`fit_gaussians` starts from for ``init``: ``"points"``, ``"random"`` or
    ``"ply"`` (Gaussians given); ``None`` means the sparse points when the scene has them."""
    if isinstance(init, Gaussians):
        return "ply"
    return init or ("points" if _has_points(scene) else "random")


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


BACKGROUND_NAME = "background.json"


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
    continue from it (its config is used, except ``steps`` and ``checkpoint_every``)."""
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
    if ck is None and config.background_from_images:
        config = replace(config, background=border_color(scene, train_views), background_from_images=False)

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

    targets = {i: torch.from_numpy(scene.image(i)).to(device) for i in train_views}
    k = g.sh.shape[1]

    def save_checkpoint(step: int) -> None:
        if _state_finite(g, adam) and (
            env is None or bool(torch.isfinite(env.sh).all())
        ):  # never persist a broken state
            state = _checkpoint(step, g, adam, stats, config, generator, sampler, loss_curve, skipped, train_time)
            if env is not None:
                assert env_adam is not None  # created together with env
                state["environment"] = {"sh": env.sh.detach().cpu().clone(), "optimizer": env_adam.state_dict()}
            save_torch(ck_path, state)

    end = config.steps if stop_after is None else min(config.steps, stop_after)
    bar = tqdm(total=config.steps, initial=start, disable=not progress, desc="fit-gaussians", dynamic_ncols=True)
    t_train = time.perf_counter()
    ema = None
    step = start
    bad_run = 0  # skipped steps in a row: MAX_BAD_STEPS of them stop the fit
    coarse_targets: dict[tuple[int, float], Tensor] = {}
    step_times: list[float] = []
    for step in range(start + 1, end + 1):
        t_step = time.perf_counter()
        if step % config.sh_degree_interval == 0 and g.sh_degree < g.max_sh_degree:
            g.sh_degree += 1
        view = sampler.next()
        camera = scene.cameras[view]
        target = targets[view]
        factor = resolution_factor(config, step)
        if factor != 1.0:
            camera = camera.downscaled(factor)
            if (view, factor) not in coarse_targets:
                coarse_targets[(view, factor)] = downsample_image(target, camera.height, camera.width)
            target = coarse_targets[(view, factor)]
        elif coarse_targets:
            coarse_targets.clear()  # the schedule has ended
        if config.depth_spread_weight > 0:
            out, spread = _render_with_depth_spread(g, camera, config, extent, env)
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
            assert env_adam is not None  # created together with env
            env_adam.zero_grad(set_to_none=True)
        loss.backward()
        # Parameter gradients are checked by the optimiser; it refuses non-finite steps.
        grads_ok = bool(torch.isfinite(loss)) and (
            out.means2d.grad is None or bool(torch.isfinite(out.means2d.grad).all())
        )
        env_ok = env is None or (env.sh.grad is not None and bool(torch.isfinite(env.sh.grad).all()))
        ok = grads_ok and env_ok and adam.step(g.params(), learning_rates(config, step, extent, k, device))
        if ok and env is not None:
            assert env_adam is not None  # created together with env
            env_adam.step()
        g.zero_grad(set_to_none=True)
        if not ok:
            skipped += 1
            bad_run += 1
            if bad_run >= MAX_BAD_STEPS:
                bar.close()
                raise _fit_stopped(step, f"the last {bad_run} steps")
        else:
            bad_run = 0
            if step < config.densify_until and out.means2d.grad is not None:
                stats.add(out.means2d.grad, out.radii, camera.width, camera.height)
            lv = float(loss.detach())
            ema = lv if ema is None else 0.9 * ema + 0.1 * lv
            if step % config.log_every == 0 or step == 1:
                loss_curve.append((step, lv))
            if step % config.log_every == 0 and progress:
                bar.set_postfix(
                    loss=f"{ema:.4f}", psnr=f"{psnr(image.detach().clamp(0, 1), target):.2f}", G=g.num, refresh=False
                )
        if step < config.densify_until:
            if step > config.densify_from and step % config.densify_every == 0:
                densify_and_prune(
                    g, adam, stats, config, extent, prune_big=0 < config.opacity_reset_every < step, generator=generator
                )
                stats = DensifyStats.zeros(g.num, device)
            if config.opacity_reset_every and step % config.opacity_reset_every == 0:
                reset_opacity(g, adam)
        step_times.append(time.perf_counter() - t_step)
        bar.update(1)
        if config.checkpoint_every and step % config.checkpoint_every == 0:
            train_time += time.perf_counter() - t_train
            t_train = time.perf_counter()
            save_checkpoint(step)
    bar.close()
    if step_times and bad_run == len(step_times):
        raise _fit_stopped(step, f"all {bad_run} steps of this run")
    train_time += time.perf_counter() - t_train
    final = max(step, start)
    save_checkpoint(final)

    report = evaluate(
        g, scene, train_views, test_views, config, extent, renders_dir=out_dir / TEST_RENDERS_DIR, env=env
    )
    report.update(
        steps=final,
        train_time_s=train_time,
        skipped_steps=skipped,
        resumed_from=None if ck is None else int(ck["step"]),
        loss_curve=_subsample(loss_curve, 200),
        config=config.to_dict(),
        threads=torch.get_num_threads(),
    )
    if step_times:
        report.update(
            step_time_median_s=float(np.median(step_times)), step_time_p95_s=float(np.percentile(step_times, 95))
        )
    write_ply(out_dir / PLY_NAME, g)  # refuses non-finite values (cannot happen: steps are guarded)
    if env is not None:
        write_json(out_dir / BACKGROUND_NAME, env.to_dict())
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
) -> dict:
    """Mean PSNR over train and test views; with ground truth, the median absolute error of the
    rendered expected depth over pixels with alpha > 0.5 of the test views (train views if none).
    With ``renders_dir``, each held-out view is written there as ``<stem>.png`` (render on the
    left, photo on the right) and ``<stem>.npy`` (the render, float32 [H, W, 3])."""
    from ..io import write_npy, write_png

    device = torch.device(config.device)

    def view_psnr(i: int):
        out = _render(g, scene.cameras[i], config, env)
        return psnr(out.features.clamp(0, 1), torch.from_numpy(scene.image(i)).to(device)), out

    train_psnr = float(np.mean([view_psnr(i)[0] for i in train_views]))
    test_psnr, errors = None, []
    depth_views = test_views or train_views
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
    gt = scene.ground_truth
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
