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
*unnormalised* ``phi_d`` exactly as Eq. 6 is written. The softmax runs over the field's scales
(all ``d`` when ``k = 1``; the supervised prefix lengths when ``k > 1``, because only those are
scale-aware features; dimensions past ``k * floor(D / k)`` then get weight 0).

Weights. ``"eq6"`` is Eq. 6 at temperature ``T``: ``T = 1`` (:data:`PAPER_TEMPERATURE`, option
value ``paper``) is the paper; ``T -> infinity`` (option value ``uniform``) gives ``gamma = 1 / S``,
the plain mean of the scale features. With unit-scale embeddings the scores are small (|score|
<~ 1), so at ``T = 1`` gamma is near uniform on average, but not per Gaussian: it follows the
unnormalised ``phi_d``'s norms and the canonical phrases. n2f2's default, ``"unit"`` (:data:`DEFAULT_WEIGHTS`), is
the mean of the *normalised* scale features, ``(1 / S) sum_d phi_d / max(|phi_d|, eps)``, i.e.
``gamma_d = 1 / (S max(|phi_d|, eps))`` (the relevancy's own normalisation,
:mod:`n2f2.field.relevancy`): every scale's direction counts the same whatever its feature's
norm, and relevancy reads only directions. It ranked better than ``T = 1`` on both generated
layouts (``docs/measurements.md``, "Uniform composite weights" and "The mean of the normalised
scale features").

Every prefix quantity is computed for all scales at once with block sums followed by a
cumulative sum over blocks: ``N x D x C`` work for ``C`` directions, never ``N x D x E x D``.
"""

from __future__ import annotations

import itertools
import math
from typing import Callable, Optional

import numpy as np
import torch
from torch import Tensor

from ..field.prefix import prefix_sq_norms, to_blocks
from ..field.relevancy import NORM_EPS

# Canonical phrases of paper Eq. 6 ("object", "stuff", "thing", "part", "texture").
DEFAULT_CANONICAL: tuple[str, ...] = ("object", "stuff", "thing", "part", "texture")
PAPER_TEMPERATURE = 1.0  # T of Eq. 6 in the paper
# Composite weightings (see the module docstring): "unit", n2f2's default, and Eq. 6 ("eq6").
COMPOSITE_WEIGHTS: tuple[str, ...] = ("unit", "eq6")
DEFAULT_WEIGHTS = "unit"


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
    temperature: float = PAPER_TEMPERATURE,  # gamma = softmax(score / T); inf: uniform
) -> Tensor:  # [N, S] gamma, sums to 1 over the scales
    """``gamma^3D`` of paper Eq. 6 over the field's scales; at ``T = inf`` its limit ``1 / S``
    (the softmax of zeros), without computing the scores."""
    if not temperature > 0:
        raise ValueError(f"composite temperature must be positive, got {temperature}")
    if math.isinf(temperature):
        S = theta.shape[1] // step
        return torch.softmax(theta.new_zeros(theta.shape[0], S), dim=-1)
    return torch.softmax(canonical_scores(theta, W, canonical, step) / temperature, dim=-1)


def unit_weights(
    theta: Tensor,  # [N, D]
    W: Tensor,  # [E, D]
    step: int = 1,
) -> Tensor:  # [N, S] gamma_d = 1 / (S max(|phi_d|, eps))
    """Weights that make ``sum_d gamma_d phi_d`` the mean of the normalised scale features
    ``phi_d / max(|phi_d|, eps)`` (``"unit"``, n2f2's default). They do not sum to 1: a zero
    scale feature (an untrained field) adds nothing instead of taking all the weight."""
    norms = prefix_sq_norms(to_blocks(theta, step), W.T @ W).sqrt_().clamp_(min=NORM_EPS)  # [S, N]
    return norms.reciprocal_().T.div_(norms.shape[0]).contiguous()


def temperature_name(temperature: float) -> str | float:
    """How a composite temperature is recorded (JSON has no infinity): "uniform" for ``inf``."""
    return "uniform" if math.isinf(temperature) else float(temperature)


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
    temperature: float = PAPER_TEMPERATURE,
    chunk: int = 65536,  # Gaussians per block: bounds the [chunk, D, K] intermediate
    weights: str = "eq6",  # "eq6" (paper Eq. 6 at ``temperature``) or "unit" (unit_weights)
) -> Tensor:  # [N, D] Theta~_i, with W @ Theta~_i = the composite embedding of Gaussian i
    """``Theta~ = revcumsum(gamma^3D) (.) Theta`` (paper Eq. 7), computed once per trained field."""
    if weights not in COMPOSITE_WEIGHTS:
        raise ValueError(f"composite weights must be one of {COMPOSITE_WEIGHTS}, got {weights!r}")
    out = torch.empty_like(theta)
    D = theta.shape[1]
    for start in range(0, theta.shape[0], chunk):
        block = theta[start : start + chunk]
        if weights == "unit":
            gamma = unit_weights(block, W, step)
        else:
            gamma = composite_weights(block, W, canonical, step, temperature)
        out[start : start + chunk] = prefix_weights(gamma, D, step) * block
    return out


# ----------------------------------------------------------------------- maxima over the points
# Explicit-mode selection in 3D needs, per scale and direction, only the maximum over the points
# of the relevancy margin ``m = phi_d^ . t - max_c phi_d^ . c`` (the relevancy is ``sigmoid(10 m)``,
# increasing in ``m``), and then the margins of every point at one chosen scale per direction.
# Both use exactly the arithmetic of :func:`prefix_dot` followed by the score caches' scaling:
# the per-block dot products of its bmm, their prefix sums accumulated in float64 and rounded
# once (what torch's CPU ``cumsum`` does for float32), times ``1 / |phi_d|``, minus the negatives'
# term. So the values equal those of the ``[S, C, P]`` margins bit for bit, but they are streamed
# over the points and that tensor never exists.

MARGIN_CHUNK = 16384  # points per window of the torch path


def prefix_terms(
    blocks: Tensor,  # [S, k, P] features in block layout
    directions: Tensor,  # [S k, C] W^T t per direction (text)
) -> tuple[Tensor, Tensor]:  # terms [S, R, P], weights [S, C]
    """The per-block dot products of :func:`prefix_dot` (before its cumulative sum) as
    ``terms[s, r, p] * weights[s, c]``, ``r = 0`` when ``R = 1``, else ``r = c``. With one dimension
    per block they are single products, formed where they are used (``terms`` is ``blocks``).
    Otherwise they are the bmm of :func:`prefix_dot`, one call over all points as there (BLAS can
    round a few elements differently in a call of another shape), and the weights are ones."""
    S, k, _ = blocks.shape
    d = directions[: S * k].reshape(S, k, -1)  # [S, k, C]
    if k == 1:
        return blocks, d[:, 0, :].contiguous()
    return torch.bmm(d.transpose(1, 2), blocks), d.new_ones(S, d.shape[2])  # [S, C, P]


def _margin_max_kernel(terms, weights, inv, neg, best):
    """``best[s, c] = max(best[s, c], max_p m[s, c, p])`` (see :func:`prefix_terms` for the dot
    products). The maximum propagates NaN, as ``torch.amax`` does."""
    S, R, P = terms.shape
    C = weights.shape[1]
    T = 2048  # points per tile: the float64 running sums stay in cache
    acc = np.empty((C, T), dtype=np.float64)
    for a in range(0, P, T):
        n = min(T, P - a)
        acc[:, :n] = 0.0
        for s in range(S):
            for c in range(C):
                r = c if R > 1 else 0
                w = weights[s, c]
                m = best[s, c]
                for i in range(n):
                    v = acc[c, i] + terms[s, r, a + i] * w
                    acc[c, i] = v
                    x = np.float32(v) * inv[s, a + i] - neg[s, a + i]
                    if x > m or np.isnan(x):
                        m = x
                best[s, c] = m


def _margin_at_kernel(terms, weights, inv, neg, scales, out):
    """``out[c, p] = m[scales[c], c, p]`` (same margins as :func:`_margin_max_kernel`)."""
    _, R, P = terms.shape
    C = weights.shape[1]
    T = 2048
    acc = np.empty(T, dtype=np.float64)
    for a in range(0, P, T):
        n = min(T, P - a)
        for c in range(C):
            r = c if R > 1 else 0
            sc = scales[c]
            acc[:n] = 0.0
            for s in range(sc + 1):
                w = weights[s, c]
                for i in range(n):
                    acc[i] += terms[s, r, a + i] * w
            for i in range(n):
                out[c, a + i] = np.float32(acc[i]) * inv[sc, a + i] - neg[sc, a + i]


_COMPILED: Optional[tuple] = None  # (margin max, margin at) once compiled; () without numba


def _compiled_kernels() -> Optional[tuple]:
    """The two margin kernels compiled by numba on first use (cached on disk: a few seconds the
    first time, about one after), or None when numba is not installed. Each runs on one thread
    and releases the GIL."""
    global _COMPILED
    if _COMPILED is None:
        try:
            import numba
        except ImportError:  # pragma: no cover - numba is a declared dependency
            _COMPILED = ()
        else:  # one signature each (any strides): compiled once, not per memory layout
            f3, f2 = "float32[:, :, :]", "float32[:, :]"
            _COMPILED = (
                numba.njit(f"void({f3}, {f2}, {f2}, {f2}, {f2})", cache=True, nogil=True)(_margin_max_kernel),
                numba.njit(f"void({f3}, {f2}, {f2}, {f2}, int64[:], {f2})", cache=True, nogil=True)(_margin_at_kernel),
            )
    return _COMPILED or None


def _kernels_for(terms: Tensor, compiled: Optional[bool]) -> Optional[tuple]:
    """The compiled kernels when they apply (CPU float32, numba importable, not refused)."""
    if compiled is False or terms.device.type != "cpu" or terms.dtype != torch.float32:
        return None
    return _compiled_kernels()


def _in_threads(job: Callable[[int, int], None], num_points: int) -> int:
    """``job(a, b)`` over point ranges that split ``range(num_points)`` over torch's thread count
    (at least 65536 points each), in threads when there are several; returns how many ranges."""
    n = max(1, min(torch.get_num_threads(), num_points // 65536))
    ranges = list(itertools.pairwise([num_points * i // n for i in range(n + 1)]))
    if n == 1:
        job(0, num_points)
        return 1
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(n) as pool:
        list(pool.map(lambda r: job(*r), ranges))
    return n


def _window_margins(
    terms: Tensor, weights: Tensor, inv_norm: Tensor, neg_max: Tensor, a: int, b: int
) -> Tensor:  # [S, C, b - a]
    """The margins of points ``a:b`` at every scale with torch ops (the arithmetic of
    :func:`prefix_dot` and the score caches)."""
    raw = (terms[:, :, a:b] * weights[:, :, None]).cumsum_(dim=0)  # [S, C, p]
    return raw.mul_(inv_norm[:, :, a:b]).sub_(neg_max[:, :, a:b])


@torch.no_grad()
def prefix_margin_max(
    terms: Tensor,  # [S, R, P] from :func:`prefix_terms`
    weights: Tensor,  # [S, C]
    inv_norm: Tensor,  # [S, 1, P] 1 / max(|phi_d|, eps)
    neg_max: Tensor,  # [S, 1, P] max_c phi_d^ . c
    compiled: Optional[bool] = None,  # None: the numba kernels on CPU float32 when numba imports
) -> Tensor:  # [S, C] max over the points of the margin phi_d^ . t - max_c phi_d^ . c
    """Per scale and direction, the largest relevancy margin over the points (see above):
    ``O(S C P)`` work, memory ``O(S C)`` per thread (compiled) or per window (torch)."""
    S, _, P = terms.shape
    C = weights.shape[1]
    kernels = _kernels_for(terms, compiled)
    if kernels is not None:
        t, w = terms.detach().numpy(), weights.detach().numpy()
        inv, neg = inv_norm.detach()[:, 0].numpy(), neg_max.detach()[:, 0].numpy()
        bests: dict[int, np.ndarray] = {}

        def job(a: int, b: int) -> None:
            best = bests.setdefault(a, np.full((S, C), -np.inf, dtype=np.float32))
            kernels[0](t[:, :, a:b], w, inv[:, a:b], neg[:, a:b], best)

        _in_threads(job, P)
        out = np.full((S, C), -np.inf, dtype=np.float32)
        for best in bests.values():
            np.maximum(out, best, out=out)  # propagates NaN like the kernel
        return torch.from_numpy(out)
    best = terms.new_full((S, C), float("-inf"))
    for a in range(0, P, MARGIN_CHUNK):
        m = _window_margins(terms, weights, inv_norm, neg_max, a, a + MARGIN_CHUNK)
        best = torch.maximum(best, m.amax(dim=-1))
    return best


@torch.no_grad()
def prefix_margin_at(
    terms: Tensor,  # [S, R, P] from :func:`prefix_terms`
    weights: Tensor,  # [S, C]
    inv_norm: Tensor,  # [S, 1, P]
    neg_max: Tensor,  # [S, 1, P]
    scales: Tensor,  # [C] int: one scale index per direction
    compiled: Optional[bool] = None,
) -> Tensor:  # [C, P] margin of every point at its direction's scale
    """The margins of :func:`prefix_margin_max` at one scale per direction, for every point."""
    P = terms.shape[2]
    C = weights.shape[1]
    out = terms.new_empty(C, P)
    kernels = _kernels_for(terms, compiled)
    if kernels is not None:
        t, w = terms.detach().numpy(), weights.detach().numpy()
        inv, neg = inv_norm.detach()[:, 0].numpy(), neg_max.detach()[:, 0].numpy()
        sc, o = scales.to("cpu", torch.int64).numpy(), out.numpy()
        _in_threads(lambda a, b: kernels[1](t[:, :, a:b], w, inv[:, a:b], neg[:, a:b], sc, o[:, a:b]), P)
        return out
    cols = torch.arange(C, device=terms.device)
    scales = scales.to(terms.device)
    for a in range(0, P, MARGIN_CHUNK):
        out[:, a : a + MARGIN_CHUNK] = _window_margins(terms, weights, inv_norm, neg_max, a, a + MARGIN_CHUNK)[
            scales, cols
        ]
    return out
