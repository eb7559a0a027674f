"""The training loss (paper eq. 5): ``L2 + lambda * (1 - cos)`` between the scale-aware feature
``phi = W (B(s) * theta)`` and the teacher embedding, as the paper writes it
(:func:`hierarchical_loss`) and as training computes it, in the field's D dims instead of the
teacher's E (:func:`projected_loss`, and :func:`prefix_projected_loss` for prefix masks)."""

from __future__ import annotations

from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor

from .numba_prefix import prefix_dot, prefix_sum


def hierarchical_loss(
    phi: Tensor,  # [P, E] scale-aware features
    target: Tensor,  # [P, E] teacher embeddings
    cos_weight: float,
) -> tuple[Tensor, Tensor, Tensor]:
    """``L2 + lambda * L_cos`` (paper eq. 5): L2 is the mean squared error over pixels and
    embedding dims; L_cos the mean cosine distance ``1 - cos(phi, target)``. Returns
    ``(loss, l2, cos)``."""
    l2 = F.mse_loss(phi, target)
    cos = (1.0 - F.cosine_similarity(phi, target, dim=-1, eps=1e-8)).mean()
    return l2 + cos_weight * cos, l2, cos


def projected_loss(
    x: Tensor,  # [P, D] B(s) * theta(u), the masked features
    W: Tensor,  # [E, D] the field's projection
    targets: Tensor,  # [T, E] the distinct teacher embeddings of the batch
    index: Tensor,  # [P] long, each pixel's row of ``targets``
    cos_weight: float,
    weight: Optional[Tensor] = None,  # [P] each row's share of the loss (PixelBatch.weight); None: 1 each
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`hierarchical_loss` of ``phi = x W^T`` against ``targets[index]``, computed in the D
    field dims instead of the E teacher dims: with ``G = W^T W`` and ``u = W^T t``,
    ``|phi - t|^2 = x G x - 2 u.x + |t|^2`` and ``cos(phi, t) = u.x / (sqrt(x G x) |t|)``
    (each norm clamped at 1e-8, as ``F.cosine_similarity`` clamps them). ``u`` is computed once per distinct
    target: a batch samples a few hundred segments for thousands of pixels. Same value and
    gradients up to float rounding, about half the work when D < E. With ``weight``, both terms
    are weighted means over the rows (``sum(w * term) / sum(w)``): rows of a pixel whose weights
    sum to 1 give that pixel's expected loss."""
    E = W.shape[0]
    gx = x @ (W.t() @ W)  # [P, D]
    # index_select, not [index]: its backward (index_add) sums in the same order whatever the
    # thread count. The matrix products' sums are ordered by the BLAS, which may split them by
    # thread (MKL on AVX-512 does): runs on 1 and 2 threads agree to float32 rounding.
    u = (targets @ W).index_select(0, index)  # [P, D]
    tt = (targets * targets).sum(1).index_select(0, index)  # [P]
    return _loss_from_products((gx * x).sum(1), (u * x).sum(1), tt, E, cos_weight, weight)


def _loss_from_products(
    xgx: Tensor,  # [R] x G x = |phi|^2 of each row
    ux: Tensor,  # [R] u.x = phi.t
    tt: Tensor,  # [R] |t|^2
    E: int,
    cos_weight: float,
    weight: Optional[Tensor],  # [R] or None
) -> tuple[Tensor, Tensor, Tensor]:
    """``(L2 + lambda * (1 - cos), L2, 1 - cos)`` from the rows' inner products: means over the
    rows, weighted means (``sum(w * term) / sum(w)``) with ``weight``."""
    norms = torch.sqrt(xgx.clamp(min=1e-16)) * torch.sqrt(tt.clamp(min=1e-16))  # |phi|, |t| each >= 1e-8
    if weight is None:
        l2 = (xgx - 2.0 * ux + tt).sum() / (xgx.shape[0] * E)
        cos = (1.0 - ux / norms).mean()
    else:
        total = weight.sum()
        l2 = (weight * (xgx - 2.0 * ux + tt)).sum() / (total * E)
        cos = (weight * (1.0 - ux / norms)).sum() / total
    return l2 + cos_weight * cos, l2, cos


def prefix_projected_loss(
    theta: Tensor,  # [P, D] theta(u) per pixel
    row: Tensor,  # [R] long, each row's pixel
    dims: Tensor,  # [R] long in [1, D], each row's M(s): its mask B(s) keeps the first M(s) dims
    W: Tensor,  # [E, D] the field's projection
    targets: Tensor,  # [T, E] the distinct teacher embeddings of the batch
    index: Tensor,  # [R] long, each row's row of ``targets``
    cos_weight: float,
    weight: Optional[Tensor] = None,  # [R] each row's share of the loss; None: 1 each
) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`projected_loss` of the rows ``x_r = theta[row_r] * B(s_r)`` when every B(s) is a
    prefix mask (nested and flat fields), with the D x D work done once per pixel instead of once
    per row. ``x G x`` over the first M dims is a prefix sum: with ``a_k = theta_k (2 sum_{j<k}
    G_kj theta_j + G_kk theta_k)``, ``x_r G x_r = sum_{k < M_r} a_k`` of the row's pixel. Same
    value and gradients up to float rounding."""
    E = W.shape[0]
    G = W.t() @ W  # [D, D]
    a = theta * (2.0 * (theta @ torch.tril(G, diagonal=-1).t()) + theta * torch.diagonal(G))  # [P, D]
    last = dims.long() - 1  # [R] the row's last kept dim
    # Compiled on CPU; elsewhere cumulative sums and flat index_selects (not advanced indexing:
    # their backward sums in a fixed order on any thread count). The products with G and W
    # follow the BLAS's order (see projected_loss).
    xgx = prefix_sum(a, row, last)  # [R]
    ux = prefix_dot(targets @ W, theta, index, row, last)  # [R]
    tt = (targets * targets).sum(1).index_select(0, index)  # [R]
    return _loss_from_products(xgx, ux, tt, E, cos_weight, weight)
