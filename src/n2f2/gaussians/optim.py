"""The Gaussian fit's optimisation (3DGS): the photometric loss (L1 + D-SSIM), Adam with per-parameter
learning rates and a row layout that follows densification, the position-rate schedule, and
adaptive density control (clone, split, prune, opacity reset)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Union

import torch
import torch.nn.functional as F
from torch import Tensor

from .fit_config import FitConfig
from .model import Gaussians, inverse_sigmoid, quat_to_rotmat


# ------------------------------------------------------------------------------------ losses
def _gaussian_1d(size: int, sigma: float, device, dtype) -> Tensor:  # [size], sums to 1
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def blur_reference(
    maps: Tensor,  # [K, H, W]
    g: Tensor,  # [S] the window along each axis, S odd
) -> Tensor:  # [K, H, W]
    """Each map correlated with ``g`` along x, then along y, with zero padding: with a separable
    window this is the same sum as the 2D window, as a 1xS then an Sx1 grouped convolution (on a
    CPU the 2D grouped convolution cost ~10x more and was a quarter of a fitting step at 370x250
    pixels). The reference of :func:`n2f2.gaussians.numba_ssim.blur_numba`."""
    k, s = maps.shape[0], g.shape[0]
    pad = s // 2
    x = F.conv2d(maps[None], g.view(1, 1, 1, -1).expand(k, 1, 1, s), padding=(0, pad), groups=k)
    return F.conv2d(x, g.view(1, 1, -1, 1).expand(k, 1, s, 1), padding=(pad, 0), groups=k)[0]


def blur(maps: Tensor, g: Tensor) -> Tensor:  # [K, H, W], [S] -> [K, H, W]
    """:func:`blur_reference`, compiled on CPU (:mod:`n2f2.gaussians.numba_ssim`)."""
    from . import numba_ssim

    return numba_ssim.blur_numba(maps, g) if numba_ssim.usable(maps) else blur_reference(maps, g)


def ssim(
    img1: Tensor,  # [H, W, C]
    img2: Tensor,  # [H, W, C]
    window_size: int = 11,
    sigma: float = 1.5,
) -> Tensor:  # [] mean SSIM
    """Mean SSIM with an 11x11 Gaussian window (sigma 1.5), zero padding, as 3DGS's ``ssim``: the
    window's two 1D passes (:func:`blur`) over the five maps at once."""
    c = img1.shape[-1]
    a = img1.permute(2, 0, 1)
    b = img2.permute(2, 0, 1)
    maps = torch.cat([a, b, a * a, b * b, a * b])  # [5C, H, W]
    maps = blur(maps, _gaussian_1d(window_size, sigma, a.device, a.dtype))
    mu1, mu2, e11, e22, e12 = maps.split(c)
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

    def __init__(self, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-15, compiled: bool = True) -> None:
        self.betas = betas
        self.eps = eps
        # CPU float32 parameters take the compiled update (n2f2.gaussians.numba_adam); the
        # tensor operations below are its reference and every other device's update.
        self.compiled = compiled
        self.exp_avg: dict[str, Tensor] = {}
        self.exp_avg_sq: dict[str, Tensor] = {}
        self.step_count: dict[str, int] = {}

    @torch.no_grad()
    def step(self, params: dict[str, Tensor], lrs: dict[str, Union[float, Tensor]]) -> bool:
        """One Adam step for every parameter that has a gradient. Returns False, changing
        nothing, when a gradient is not finite or so large that its square overflows (the only
        ways a step from a finite state can produce a non-finite one)."""
        from . import numba_adam

        b1, b2 = self.betas
        live = {name: p for name, p in params.items() if p.grad is not None}
        grads = [p.grad for p in live.values() if p.grad is not None and p.grad.numel()]
        limit = math.sqrt(torch.finfo(torch.float32).max) / 16.0
        # Each gradient's largest magnitude (NaN propagates through the max and fails the
        # comparison): one check for all, instead of isfinite and abs > limit per tensor.
        peaks = [g.abs().amax() for g in grads]
        if peaks and not bool((torch.stack(peaks) <= limit).all()):
            return False
        for name, p in live.items():
            g = p.grad
            assert g is not None  # as above
            if name not in self.exp_avg:
                self.exp_avg[name], self.exp_avg_sq[name] = torch.zeros_like(p), torch.zeros_like(p)
            m, v = self.exp_avg[name], self.exp_avg_sq[name]
            t = self.step_count.get(name, 0) + 1
            self.step_count[name] = t
            if self.compiled and numba_adam.usable([p, g, m, v]):
                numba_adam.adam_update(p, g, m, v, lrs[name], self.betas, t, self.eps)
                continue
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
        g = means2d_grad * torch.tensor([width / 2.0, height / 2.0], device=means2d_grad.device)
        # Whole-tensor updates (no boolean indexing, which finds the visible rows once per use):
        # the hidden rows add exactly 0, and their radius 0 never raises a maximum that starts at 0.
        self.grad_accum += torch.where(visible, g.norm(dim=-1), 0.0)
        self.count += visible
        torch.maximum(self.max_radii, radii.float() / max(width, height), out=self.max_radii)

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
