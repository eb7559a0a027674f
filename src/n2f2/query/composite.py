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


def to_blocks(
    theta: Tensor,  # [P, D] features, one row per point
    step: int = 1,
) -> Tensor:  # [S, k, P] contiguous, S = floor(D / k); dims past S k are dropped
    """Block layout of prefix computations: dimension ``j`` goes to block ``j // k``, points
    last, so scale sums are batched matmuls whose results are already ``[S, C, P]``."""
    P, D = theta.shape
    S = D // step
    return theta[:, : S * step].T.reshape(S, step, P).contiguous()


def prefix_dot(
    blocks: Tensor,  # [S, k, P] features in block layout (:func:`to_blocks`)
    directions: Tensor,  # [S k, C] per-dimension terms, e.g. W^T t for text embeddings t
) -> Tensor:  # [S, C, P]
    """``out[s, c, p] = sum_{j < (s + 1) k} theta[p, j] * directions[j, c]``: the dot products
    ``phi_{d_s} . t_c`` of every prefix feature with every direction whose field-space image is
    ``directions = W^T t``.

    Per-block sums are one batched matmul (``P x D x C`` work); a cumulative sum over the ``S``
    blocks turns them into prefix sums."""
    S, k, _ = blocks.shape
    d = directions[: S * k].reshape(S, k, -1).transpose(1, 2)  # [S, C, k]
    return torch.bmm(d, blocks).cumsum_(dim=0)  # [S, C, P]


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


def canonical_scores(
    theta: Tensor,  # [N, D] Gaussian features Theta_i
    W: Tensor,  # [E, D] projection
    canonical: Tensor,  # [K, E] embeddings of the canonical phrases
    step: int = 1,
) -> Tensor:  # [N, S] max_k phi_{i,d_s} . phi_canon_k
    """The argument of the softmax in paper Eq. 6, for every scale at once (``N x D x K``)."""
    dots = prefix_dot(to_blocks(theta, step), (canonical @ W).T)  # [S, K, N]
    return dots.amax(dim=1).T


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
