"""The 3D Gaussian Splatting model: one row per Gaussian, stored in the unconstrained
parameterisation that 3DGS optimises (log-scales, opacity logits, unnormalised quaternions).

Layout (as in original 3DGS / gsplat):

* ``means [N, 3]`` world-space centres.
* ``quats [N, 4]`` rotation as (w, x, y, z), *not* normalised; renderers normalise.
* ``log_scales [N, 3]`` per-axis standard deviations, stored as log.
* ``opacity_logits [N]`` opacity before the sigmoid.
* ``sh [N, K, 3]`` spherical-harmonic colour coefficients, K = (max_sh_degree + 1) ** 2;
  ``sh[:, 0]`` is the DC term (colour = SH_C0 * dc + 0.5 when only degree 0 is active).
"""

from __future__ import annotations

import math
from typing import Optional

import torch
from torch import Tensor, nn

from ..render.sh import SH_C0, num_sh_bases  # noqa: F401 - re-exported: one definition of the SH layout

# Names of the per-Gaussian parameters, in a fixed order (optimiser, checkpoints and densification
# iterate over this tuple so they always agree on which rows belong together).
PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh")


def sh_degree_from_bases(k: int) -> int:
    """Inverse of :func:`num_sh_bases`; raises ValueError when ``k`` is not a square."""
    d = math.isqrt(int(k)) - 1
    if d < 0 or num_sh_bases(d) != k:
        raise ValueError(f"{k} SH coefficients per channel is not (degree + 1)^2 for any degree")
    return d


def rgb_to_sh(rgb: Tensor) -> Tensor:  # [..., 3] in [0, 1] -> [..., 3] DC coefficient
    """DC SH coefficient whose degree-0 colour is ``rgb`` (3DGS ``RGB2SH``)."""
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(dc: Tensor) -> Tensor:  # [..., 3] DC coefficient -> [..., 3] colour
    """Degree-0 colour of a DC coefficient (3DGS ``SH2RGB``)."""
    return dc * SH_C0 + 0.5


def inverse_sigmoid(x: Tensor) -> Tensor:
    return torch.log(x / (1.0 - x))


def quat_to_rotmat(quats: Tensor) -> Tensor:  # [N, 4] wxyz, any norm -> [N, 3, 3]
    """Rotation matrices of (normalised) wxyz quaternions, the model's orientation convention.
    (The renderer keeps its own copy in a kernel-friendly [3, 3, N] layout.)"""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(quats.shape[:-1] + (3, 3))


class Gaussians(nn.Module):
    """A 3DGS scene. Parameters are ``nn.Parameter`` so any torch optimiser can fit them;
    densification replaces them with :meth:`set_params`.

    ``sh_degree`` is the *active* SH degree (the fitting schedule raises it over time; renderers
    evaluate only the first ``(sh_degree + 1) ** 2`` coefficients); ``max_sh_degree`` is fixed by
    the size of ``sh``.
    """

    def __init__(
        self,
        means: Tensor,  # [N, 3]
        quats: Tensor,  # [N, 4] wxyz, unnormalised
        log_scales: Tensor,  # [N, 3]
        opacity_logits: Tensor,  # [N]
        sh: Tensor,  # [N, K, 3]
        sh_degree: Optional[int] = None,  # active degree; default: the maximum that ``sh`` holds
    ) -> None:
        super().__init__()
        n = means.shape[0]
        shapes = {"means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,)}
        given = {"means": means, "quats": quats, "log_scales": log_scales, "opacity_logits": opacity_logits}
        for name, shape in shapes.items():
            if tuple(given[name].shape) != shape:
                raise ValueError(f"Gaussians.{name} must have shape {list(shape)}, got {list(given[name].shape)}")
        if sh.ndim != 3 or sh.shape[0] != n or sh.shape[2] != 3:
            raise ValueError(f"Gaussians.sh must have shape [N={n}, K, 3], got {list(sh.shape)}")
        self.max_sh_degree = sh_degree_from_bases(sh.shape[1])
        if sh_degree is None:
            sh_degree = self.max_sh_degree
        if not 0 <= int(sh_degree) <= self.max_sh_degree:
            raise ValueError(f"active SH degree {sh_degree} outside [0, {self.max_sh_degree}]")
        self.sh_degree = int(sh_degree)
        self.means = nn.Parameter(means.detach().float().contiguous())
        self.quats = nn.Parameter(quats.detach().float().contiguous())
        self.log_scales = nn.Parameter(log_scales.detach().float().contiguous())
        self.opacity_logits = nn.Parameter(opacity_logits.detach().float().contiguous())
        self.sh = nn.Parameter(sh.detach().float().contiguous())

    # ------------------------------------------------------------------ activated views
    @property
    def scales(self) -> Tensor:  # [N, 3]
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> Tensor:  # [N]
        return torch.sigmoid(self.opacity_logits)

    @property
    def normalized_quats(self) -> Tensor:  # [N, 4]
        return torch.nn.functional.normalize(self.quats, dim=-1)

    @property
    def num(self) -> int:
        return int(self.means.shape[0])

    def __len__(self) -> int:
        return self.num

    @property
    def device(self) -> torch.device:
        return self.means.device

    def extra_repr(self) -> str:
        return f"num={self.num}, sh_degree={self.sh_degree}, max_sh_degree={self.max_sh_degree}"

    # ------------------------------------------------------------------ editing
    def params(self) -> dict[str, Tensor]:
        """The parameters by name, in :data:`PARAM_NAMES` order."""
        return {name: getattr(self, name) for name in PARAM_NAMES}

    @torch.no_grad()
    def set_params(self, **tensors: Tensor) -> None:
        """Replace parameters (all with the same new row count, or only ones that keep N).

        Fresh ``nn.Parameter`` objects are created, so an optimiser holding the old ones must be
        rebuilt (the fitting loop keys its state by name, not by object)."""
        for name, value in tensors.items():
            if name not in PARAM_NAMES:
                raise KeyError(f"unknown Gaussian parameter {name!r}")
            setattr(self, name, nn.Parameter(value.detach().contiguous()))
        counts = {name: getattr(self, name).shape[0] for name in PARAM_NAMES}
        if len(set(counts.values())) != 1:
            raise ValueError(f"Gaussian parameters disagree on N: {counts}")

    def subset(self, mask: Tensor) -> "Gaussians":  # [N] bool, or [M] long indices
        """A new, independent model with the selected Gaussians (same active SH degree)."""
        with torch.no_grad():
            return Gaussians(**{name: p[mask].clone() for name, p in self.params().items()}, sh_degree=self.sh_degree)

    def clone(self) -> "Gaussians":
        return self.subset(torch.arange(self.num, device=self.device))

    @staticmethod
    def empty(sh_degree: int = 3, device: torch.device | str | None = None) -> "Gaussians":
        k = num_sh_bases(sh_degree)
        z = lambda *s: torch.zeros(*s, device=device)  # noqa: E731
        return Gaussians(z(0, 3), z(0, 4), z(0, 3), z(0), z(0, k, 3))

    @torch.no_grad()
    def finite(self) -> bool:
        """True when every parameter is finite (used to keep NaNs out of checkpoints)."""
        return all(bool(torch.isfinite(p).all()) for p in self.params().values())
