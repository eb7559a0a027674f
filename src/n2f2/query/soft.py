"""The ``soft`` query mode ("soft explicit"): per query, a softmax-weighted average of the relevancy
at every scale of the field, written once here and used by the query engine (2D views and 3D
Gaussians) and the evaluation runner.

For a query ``q`` and the field's scales ``s = 1..S`` (a nested field's supervised prefix lengths,
a flat field's one scale), with ``rel_s(q, p)`` the relevancy (:mod:`n2f2.field.relevancy`) of a
point ``p`` (a pixel of the view, or a Gaussian) at scale ``s``::

    peak_s(q) = max_p rel_s(q, p)                   (over the view's pixels / the Gaussians)
    w_s(q)    = softmax_s(peak_s(q) / tau)          tau = SOFT_TEMPERATURE
    soft(q, p) = sum_s w_s(q) rel_s(q, p)

Explicit mode keeps the one scale with the highest peak (``tau -> 0``, with LERF's "max" rule);
soft mode blends the scales whose peaks are within a few ``tau`` of the best, so a query whose
best scales are close does not flip between them. With one scale (a flat field) the weight is
exactly 1 and soft equals explicit. Only the prefix fields (variants ``nested`` and ``flat``)
answer it; the 3-level fields (variant ``levels``, the lift) keep their levels / oracle modes.

``tau = 0.01`` (relevancy is in (0, 1)): chosen on the two generated demo layouts (tabletop,
lounge), where 0.003 and 0.03 scored about the same; it is not a paper setting.
"""

from __future__ import annotations

import torch
from torch import Tensor

SOFT_TEMPERATURE = 0.01  # tau of w = softmax(peak / tau); chosen on the demo layouts (see above)
# A scale whose weight is below NEGLIGIBLE_WEIGHT / S for every query may be left out of the sum:
# the S at most such scales add at most 2^-24 (float32's unit roundoff) to a relevancy in (0, 1).
NEGLIGIBLE_WEIGHT = 2.0**-24


def soft_weights(
    peaks: Tensor,  # [Q, S] highest relevancy over the points at each scale
    temperature: float = SOFT_TEMPERATURE,
) -> Tensor:  # [Q, S] w_s(q), sums to 1 over the scales
    """``softmax_s(peak_s / tau)``."""
    if not temperature > 0:
        raise ValueError(f"soft temperature must be positive, got {temperature}")
    return torch.softmax(peaks / temperature, dim=-1)


def soft_combine(
    relevancy: Tensor,  # [S, Q, P] relevancy at each scale (or at the scales kept, matching weights)
    weights: Tensor,  # [Q, S] w_s(q)
) -> Tensor:  # [Q, P] sum_s w_s(q) rel_s(q, p)
    """The weighted sum over the scales."""
    return torch.einsum("sqp,qs->qp", relevancy, weights.to(relevancy.dtype))


def soft_relevancy(
    relevancy: Tensor,  # [S, Q, P] relevancy of every point at every scale
    temperature: float = SOFT_TEMPERATURE,
) -> tuple[Tensor, Tensor]:  # soft relevancy [Q, P], peaks [Q, S]
    """Soft mode from the relevancy at every scale (a rendered view's ``[S, Q, H W]`` maps): the
    peaks are its maxima over the points."""
    peaks = relevancy.amax(dim=-1).T.contiguous()  # [Q, S]
    return soft_combine(relevancy, soft_weights(peaks, temperature)), peaks


def weighed_scales(weights: Tensor) -> Tensor:  # [Q, S] -> [K] int64, increasing
    """The scales some query weighs at least ``NEGLIGIBLE_WEIGHT / S`` (the others may be left out
    of :func:`soft_combine` for every query, see :data:`NEGLIGIBLE_WEIGHT`)."""
    S = weights.shape[-1]
    return torch.nonzero((weights >= NEGLIGIBLE_WEIGHT / S).any(dim=0)).flatten()
