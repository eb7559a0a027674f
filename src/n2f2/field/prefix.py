"""Prefix features of a nested field, for every prefix length at once: the block layout of the
dimensions and the squared norms ``|W[:, :d] theta[:d]|^2`` of all prefixes, without forming any
``E``-dimensional vector. The query stage (:mod:`n2f2.query.composite`) and the hierarchy's node
embeddings (:mod:`n2f2.hierarchy.nodes`) use them."""

from __future__ import annotations

import torch
from torch import Tensor


def to_blocks(
    theta: Tensor,  # [P, D] features, one row per point
    step: int = 1,
) -> Tensor:  # [S, k, P] contiguous, S = floor(D / k); dims past S k are dropped
    """Block layout of prefix computations: dimension ``j`` goes to block ``j // k``, points
    last, so scale sums are batched matmuls whose results are already ``[S, C, P]``."""
    P, D = theta.shape
    S = D // step
    return theta[:, : S * step].T.reshape(S, step, P).contiguous()


def prefix_sq_norms(
    blocks: Tensor,  # [S, k, P] features in block layout
    gram: Tensor,  # [D, D] W^T W (only the first S k rows / columns are used)
) -> Tensor:  # [S, P] |phi_{d_s}|^2
    """Squared norms of all prefix features ``|W[:, :d] theta[:d]|^2`` for the scales
    ``d_s = (s + 1) k``, without forming any ``E``-dimensional vector.

    ``|phi_d|^2 = sum_{j <= d} theta_j (2 sum_{i < j} G_ji theta_i + G_jj theta_j)`` with
    ``G = W^T W`` (the recurrence ``n_d = n_{d-1} + 2 theta_d G[d, :d] theta[:d] + G_dd theta_d^2``):
    the inner sums for all ``j`` are one ``[D, D] x [D, P]`` matmul, the outer sum a cumulative
    sum. Clamped at 0 against rounding."""
    S, k, P = blocks.shape
    n = S * k
    g = gram[:n, :n]
    theta = blocks.reshape(n, P)  # [D', P] dimension-major
    inner = torch.tril(g, diagonal=-1) @ theta  # [D', P]: sum_{i<j} G_ji theta_i
    terms = theta * (2.0 * inner + torch.diagonal(g)[:, None] * theta)  # [D', P]
    return terms.reshape(S, k, P).sum(dim=1).cumsum_(dim=0).clamp_(min=0.0)
