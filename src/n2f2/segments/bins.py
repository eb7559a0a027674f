"""Quantised segment scales and the scale -> dimension mapping of N2F2 (paper Sec. 3.2, Table 6).

A segment's raw scale is the largest eigenvalue of the covariance of its lifted 3D points
(:mod:`n2f2.segments.lifting`). Raw scales are heavy-tailed, so the paper maps them through a
quantile transform fitted over all segments of the scene: the result ``s`` is uniform in
[0, 1), small physical size -> small ``s``. Feature dimension ``M(s) = ceil(D (1 - s))`` then
gives coarse segments (large ``s``) few dimensions and fine segments (small ``s``) many.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Union

import numpy as np

try:  # torch is a hard dependency of n2f2, but keep this module importable without it
    import torch
    from torch import Tensor
except ImportError:  # pragma: no cover
    torch = None
    Tensor = Any

ArrayLike = Union[np.ndarray, "Tensor", float]

# Largest float32 below 1: transformed scales are clipped here so s is in [0, 1) even after a
# float32 round trip (then D (1 - s) > 0 and M(s) >= 1).
ONE_MINUS_EPS = float(np.nextafter(np.float32(1.0), np.float32(0.0)))


@dataclass(frozen=True)
class QuantileScaleBins:
    """A fitted quantile transform of raw scales (as sklearn's ``QuantileTransformer`` with a
    uniform output): ``knots`` are the empirical quantiles of the fitted scales at the evenly
    spaced probabilities ``references``; transform interpolates linearly between them.

    Stored in ``bank.json`` via :meth:`to_dict` / :meth:`from_dict`.
    """

    knots: np.ndarray  # [Q] non-decreasing raw-scale quantiles
    references: np.ndarray  # [Q] probabilities in [0, 1], evenly spaced

    @staticmethod
    def fit(scales: np.ndarray, num_quantiles: int = 1000) -> "QuantileScaleBins":
        """Fit on raw scales [N] (NaN entries, i.e. dropped segments, are ignored).

        ``num_quantiles`` (default 1000, as sklearn) is capped by the number of valid scales."""
        scales = np.asarray(scales, dtype=np.float64).reshape(-1)
        scales = scales[np.isfinite(scales)]
        if scales.size == 0:
            raise ValueError("cannot fit a quantile transform: no valid (finite) scales")
        q = int(max(1, min(num_quantiles, scales.size)))
        references = np.linspace(0.0, 1.0, q) if q > 1 else np.zeros(1)
        knots = np.quantile(scales, references)
        # np.quantile is monotone up to rounding; enforce it so np.interp is well defined.
        knots = np.maximum.accumulate(knots)
        return QuantileScaleBins(knots=knots, references=references)

    def transform(self, scales: np.ndarray) -> np.ndarray:
        """Raw scales [...] -> quantised scales s in [0, 1) [...] (float64); NaN stays NaN.

        Repeated knots (ties in the data) are handled as sklearn does: average the forward
        interpolation and the interpolation of the reversed sequence, so a tied value maps to
        the middle of its probability range instead of one end."""
        x = np.asarray(scales, dtype=np.float64)
        k, r = self.knots, self.references
        if k.size == 1:
            out = np.zeros_like(x)
        else:
            out = 0.5 * (np.interp(x, k, r) - np.interp(-x, -k[::-1], -r[::-1]))
        out = np.clip(out, 0.0, ONE_MINUS_EPS)
        return np.where(np.isnan(x), np.nan, out)

    __call__ = transform

    def to_dict(self) -> dict:
        return {
            "kind": "quantile-uniform",
            "knots": [float(v) for v in self.knots],
            "references": [float(v) for v in self.references],
        }

    @staticmethod
    def from_dict(d: dict) -> "QuantileScaleBins":
        knots = np.asarray(d["knots"], dtype=np.float64)
        refs = np.asarray(d["references"], dtype=np.float64)
        if knots.shape != refs.shape or knots.ndim != 1 or knots.size == 0:
            raise ValueError("quantile transform needs equally long, non-empty knots and references")
        return QuantileScaleBins(knots=knots, references=refs)


def num_scales(D: int, k: int = 1) -> int:
    """``floor(D / k)``: how many scales (distinct prefix lengths) a nested field of ``D`` dims
    with step size ``k`` has (paper Table 6)."""
    D, k = int(D), int(k)
    if k < 1 or D < k:
        raise ValueError(f"step size k must satisfy 1 <= k <= D, got k={k}, D={D}")
    return D // k


def supervised_dims(D: int, k: int = 1) -> list[int]:
    """The scales of a nested field of ``D`` dims with step size ``k``: the prefix lengths
    ``[k, 2k, ..., k floor(D / k)]`` (1-based), coarse (short prefix) to fine, i.e. the values
    :func:`scale_to_dims` takes. With ``k = 1`` every ``d = 1..D`` is a scale, as in the paper."""
    return [k * (i + 1) for i in range(num_scales(D, k))]


def scale_to_dims(s: ArrayLike, D: int, k: int = 1):
    """Feature dimension used for quantised scale ``s`` in [0, 1):
    ``M(s) = k * ceil(floor(D / k) * (1 - s))``.

    With ``k = 1`` this is the paper's ``M(s) = ceil(D (1 - s))``. With a step size ``k``
    (paper Table 6) scales are quantised to ``floor(D / k)`` values and only the dimensions
    :func:`supervised_dims` ``= {k, 2k, ..., k floor(D / k)}`` are used. Larger ``s`` (coarser
    segment) -> fewer dimensions. Works on numpy arrays (returns int64) and torch tensors
    (returns long, same device); values are clamped to ``[k, k floor(D / k)]`` so s slightly
    outside [0, 1) from rounding is harmless.
    """
    D, k = int(D), int(k)
    n = num_scales(D, k)  # number of distinct quantised scales
    if torch is not None and isinstance(s, torch.Tensor):
        m = torch.ceil(n * (1.0 - s.double())).clamp_(1, n).long()
        return m * k
    m = np.clip(np.ceil(n * (1.0 - np.asarray(s, dtype=np.float64))), 1, n).astype(np.int64)
    return m * k


def three_level_groups(s: ArrayLike):
    """Terciles of the quantised scale, for a LangSplat-like 3-level baseline:
    0 = finest (s < 1/3, "part"-like), 1 = middle, 2 = coarsest (s >= 2/3, "group"-like).

    The order matches the ground-truth level order of the demo scene (0 = part, 1 = object,
    2 = group), not the dimension order of the field (where coarse uses the first dims).
    NaN inputs map to -1."""
    if torch is not None and isinstance(s, torch.Tensor):
        g = torch.floor(3.0 * s).clamp(0, 2)
        return torch.where(torch.isnan(s), torch.full_like(g, -1), g).long()
    s = np.asarray(s, dtype=np.float64)
    g = np.clip(np.floor(3.0 * np.nan_to_num(s, nan=0.0)), 0, 2).astype(np.int64)
    return np.where(np.isnan(s), -1, g)
