"""Prefix (scale-aware) features and the composite embedding of N2F2 (paper Sec. 3.3).

Notation. A nested field gives a point feature ``theta [D]`` and a projection ``W [E, D]``
(``E`` = text-embedding size). The scale-aware feature of prefix length ``d`` is

    phi_d = W[:, :d] @ theta[:d] = sum_{j <= d} theta_j W_j                       (paper Eq. 3)

With step size ``k`` only the prefix lengths ``d in {k, 2k, ..., k * floor(D / k)}`` are
supervised (paper Sec. 4.3, "step size"); they are the *scales* of the field, coarse (short
prefix) to fine (long prefix). With ``k = 1`` every ``d = 1..D`` is a scale, as in the paper.

Composite embedding (paper Eq. 6-7). Per Gaussian,

    gamma_i = softmax_d( max_c phi_{i,d} . phi_canon_c / T )                         (Eq. 6)
    Theta~_i = revcumsum(gamma_i) (.) Theta_i,  revcumsum_j = sum_{d >= j} gamma_d  (Eq. 7)

so that ``W @ Theta~_i = sum_d gamma_{i,d} phi_{i,d}``. The canonical-phrase scores use the
*unnormalised* ``phi_d`` exactly as Eq. 6 is written. ``T = 1`` is the paper; the team measured
that at ``T = 1`` the scores (|score| <~ 1) make gamma nearly uniform (max gamma ~ 1.15 / D),
so composite then applies an almost fixed ramp ``(D - j + 1) / D`` over dimensions; ``T`` is
exposed as a documented option and is *not* tuned here. The softmax runs over the field's
scales (all ``d`` when ``k = 1``; the supervised prefix lengths when ``k > 1``, because only
those are scale-aware features; dimensions past ``k * floor(D / k)`` then get weight 0).

Every prefix quantity is computed for all scales at once with block sums followed by a
cumulative sum over blocks: ``N x D x C`` work for ``C`` directions, never ``N x D x E x D``.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

# Canonical phrases of paper Eq. 6 ("object", "stuff", "thing", "part", "texture").
DEFAULT_CANONICAL: tuple[str, ...] = ("object", "stuff", "thing", "part", "texture")


def supervised_dims(dim: int, step: int = 1) -> list[int]:
    """Prefix lengths (1-based) that are scales of a field with ``dim`` dimensions and step size
    ``step``: ``[step, 2 step, ..., step * floor(dim / step)]``."""
    if dim < 1 or step < 1 or step > dim:
        raise ValueError(f"need 1 <= step <= dim, got dim={dim}, step={step}")
    return list(range(step, step * (dim // step) + 1, step))


def prefix_dot(
    theta: Tensor,  # [P, D] point or pixel features
    directions: Tensor,  # [D, C] per-dimension terms, e.g. W^T t for text embeddings t [E, C]
    step: int = 1,
) -> Tensor:  # [P, S, C], S = floor(D / step)
    """``out[p, s, c] = sum_{j <= d_s} theta[p, j] * directions[j, c]`` for the scales
    ``d_s = (s + 1) * step``: the dot products ``phi_{d_s} . t_c`` of every prefix feature with
    every direction whose field-space image is ``directions = W^T t``.

    Computed as per-block sums (one batched matmul, ``P x D x C`` work) and a cumulative sum
    over the ``S`` blocks."""
    P, D = theta.shape
    S = D // step
    used = S * step
    blocks = torch.bmm(
        theta[:, :used].reshape(P, S, step).transpose(0, 1),  # [S, P, k]
        directions[:used].reshape(S, step, -1),  # [S, k, C]
    )  # [S, P, C]
    return blocks.cumsum_(dim=0).transpose(0, 1)  # [P, S, C]


def prefix_sq_norms(
    theta: Tensor,  # [P, D]
    gram: Tensor,  # [D, D] W^T W
    step: int = 1,
) -> Tensor:  # [P, S] |phi_{d_s}|^2
    """Squared norms of all prefix features ``|W[:, :d] theta[:d]|^2`` for the scales
    ``d_s = (s + 1) * step``, without forming any ``E``-dimensional vector.

    ``|phi_d|^2 = sum_{j <= d} theta_j (2 sum_{i < j} G_ji theta_i + G_jj theta_j)`` with
    ``G = W^T W``: the inner sum for all ``j`` is one ``[P, D] x [D, D]`` matmul, the outer sum
    a cumulative sum. Clamped at 0 against rounding."""
    lower = torch.tril(gram, diagonal=-1)  # L[j, i] = G[j, i] for i < j
    inner = theta @ lower.T  # [P, D]: sum_{i<j} G_ji theta_i
    terms = theta * (2.0 * inner + theta * torch.diagonal(gram))  # [P, D]
    P, D = theta.shape
    S = D // step
    sums = terms[:, : S * step].reshape(P, S, step).sum(dim=-1).cumsum_(dim=-1)  # [P, S]
    return sums.clamp_(min=0.0)


def canonical_scores(
    theta: Tensor,  # [N, D] Gaussian features Theta_i
    W: Tensor,  # [E, D] projection
    canonical: Tensor,  # [K, E] embeddings of the canonical phrases
    step: int = 1,
) -> Tensor:  # [N, S] max_k phi_{i,d_s} . phi_canon_k
    """The argument of the softmax in paper Eq. 6, for every scale at once (``N x D x K``)."""
    return prefix_dot(theta, W.T @ canonical.T, step).amax(dim=-1)


def composite_weights(
    theta: Tensor,  # [N, D]
    W: Tensor,  # [E, D]
    canonical: Tensor,  # [K, E]
    step: int = 1,
    temperature: float = 1.0,  # gamma = softmax(score / T); T = 1 is the paper
) -> Tensor:  # [N, S] gamma, sums to 1 over the scales
    """``gamma^3D`` of paper Eq. 6 over the field's scales."""
    if not temperature > 0:
        raise ValueError(f"composite temperature must be positive, got {temperature}")
    return torch.softmax(canonical_scores(theta, W, canonical, step) / temperature, dim=-1)


def prefix_weights(
    gamma: Tensor,  # [N, S] weight of each scale
    dim: int,  # D
    step: int = 1,
) -> Tensor:  # [N, D] r_j = sum_{s : d_s >= j} gamma_s
    """The reversed cumulative sum of paper Eq. 7, expanded to every dimension: dimension ``j``
    belongs to all prefixes at least ``j`` long. Dimensions past the last scale get 0."""
    N, S = gamma.shape
    rev = gamma.flip(-1).cumsum(-1).flip(-1)  # [N, S]: sum over scales s' >= s
    r = rev.repeat_interleave(step, dim=-1)  # dimension j (0-based) lies in block j // step
    if S * step < dim:
        r = torch.cat([r, r.new_zeros(N, dim - S * step)], dim=-1)
    return r


def premultiply(
    theta: Tensor,  # [N, D] Gaussian features Theta_i
    W: Tensor,  # [E, D]
    canonical: Tensor,  # [K, E]
    step: int = 1,
    temperature: float = 1.0,
    chunk: int = 65536,  # Gaussians per block: bounds the [chunk, D, K] intermediate
) -> Tensor:  # [N, D] Theta~_i, with W @ Theta~_i = the composite embedding of Gaussian i
    """``Theta~ = revcumsum(gamma^3D) (.) Theta`` (paper Eq. 7), computed once per trained field."""
    out = torch.empty_like(theta)
    D = theta.shape[1]
    for start in range(0, theta.shape[0], chunk):
        block = theta[start:start + chunk]
        gamma = composite_weights(block, W, canonical, step, temperature)
        out[start:start + chunk] = prefix_weights(gamma, D, step) * block
    return out


def scale_names(dims: Sequence[int]) -> list[str]:
    """Human-readable scale labels, e.g. ``d=16``."""
    return [f"d={d}" for d in dims]
