"""Score caches of the query engine: per-point data (the pixels of a rendered view, or the
Gaussians) that turns a batch of text embeddings into relevancy at every scale of a mode with one
pass over the cache (see :mod:`n2f2.query.engine` for the modes and the fast path), and the
per-query scale choice of explicit / levels mode (:func:`select_scale`) and soft mode over the
Gaussians (:func:`soft_scales`)."""

from __future__ import annotations

from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import Protocol, Sequence, Union

import torch
from torch import Tensor

from ..field.prefix import prefix_sq_norms, to_blocks
from ..field.relevancy import inverse_norm, inverse_norm_from_sq, relevancy_from_scores
from ..segments.bins import supervised_dims
from .composite import prefix_dot, prefix_margin_at, prefix_margin_max, prefix_terms
from .soft import SOFT_TEMPERATURE, soft_combine, soft_weights, weighed_scales


class ScoreCache(Protocol):
    """Per-point data that turns text embeddings into relevancy at every scale of a mode."""

    labels: list[str]  # one per scale

    def relevancy(self, texts: Tensor) -> Tensor:  # texts [Q, E] -> [S, Q, P]
        ...


@dataclass
class CompositeCache:
    """Composite mode: ``Theta~`` at the points and its normalisation/negatives terms."""

    features: Tensor  # [P, D] Theta~ (rendered per pixel, or per Gaussian)
    W: Tensor  # [E, D]
    inv_norm: Tensor  # [P] 1 / max(|W Theta~|, eps)
    neg_max: Tensor  # [P] max_c (W Theta~)^ . c
    labels: list[str] = dc_field(default_factory=lambda: ["composite"])

    def relevancy(self, texts: Tensor) -> Tensor:  # [Q, E] -> [1, Q, P]
        q = texts @ self.W  # [Q, D]: the text in field space, once per query
        raw = q @ self.features.T  # [Q, P]: one pass over the cache (BLAS reads the transpose)
        raw.mul_(self.inv_norm)  # cosine similarity
        return relevancy_from_scores(raw, self.neg_max, inplace=True).unsqueeze(0)


@dataclass
class PrefixCache:
    """Explicit / oracle modes on a nested (or flat) field: all prefix scales at the points."""

    blocks: Tensor  # [S, k, P] raw theta in block layout (dimension j in block j // k)
    W: Tensor  # [E, D]
    dims: list[int]  # [S] prefix length of each scale
    inv_norm: Tensor  # [S, 1, P] 1 / max(|phi_d|, eps)
    neg_max: Tensor  # [S, 1, P] max_c phi_d^ . c
    labels: list[str] = dc_field(default_factory=list)

    def relevancy(self, texts: Tensor) -> Tensor:  # [Q, E] -> [S, Q, P]
        raw = prefix_dot(self.blocks, self._directions(texts))  # [S, Q, P]
        raw.mul_(self.inv_norm)
        return relevancy_from_scores(raw, self.neg_max, inplace=True)

    def _directions(self, texts: Tensor) -> Tensor:  # [Q, E] -> [D', Q] the texts in field space
        S, k, _ = self.blocks.shape
        return (texts @ self.W[:, : S * k]).T

    def terms(self, texts: Tensor) -> tuple[Tensor, Tensor]:  # [Q, E] -> [S, R, P], [S, Q]
        """The per-block dot products of the texts (:func:`n2f2.query.composite.prefix_terms`)."""
        return prefix_terms(self.blocks, self._directions(texts))


@dataclass
class LinearCache:
    """Levels mode (and oracle on a "levels" field): ``S`` fixed linear maps of theta."""

    features: Tensor  # [P, D] raw theta
    maps: Tensor  # [S, E, D] phi_s = maps[s] @ theta
    inv_norm: Tensor  # [S, 1, P]
    neg_max: Tensor  # [S, 1, P]
    labels: list[str] = dc_field(default_factory=list)

    def relevancy(self, texts: Tensor) -> Tensor:  # [Q, E] -> [S, Q, P]
        return relevancy_from_scores(self.margins(texts), self.neg_max.new_zeros(()), inplace=True)

    def margins(self, texts: Tensor) -> Tensor:  # [Q, E] -> [S, Q, P]
        """Relevancy margins ``phi^ . t - max_c phi^ . c`` (relevancy = ``sigmoid(10 margin)``)."""
        S = self.maps.shape[0]
        q = torch.einsum("sed,qe->sqd", self.maps, texts).reshape(S * texts.shape[0], -1)  # [S Q, D]
        raw = (q @ self.features.T).view(S, texts.shape[0], -1)  # [S, Q, P]
        return raw.mul_(self.inv_norm).sub_(self.neg_max)


def build_composite_cache(
    features: Tensor,  # [P, D] Theta~ at the points
    W: Tensor,  # [E, D]
    negatives: Tensor,  # [C, E] unit embeddings of the negative phrases
    chunk: int = 65536,
) -> CompositeCache:
    P = features.shape[0]
    inv = features.new_empty(P)
    neg = features.new_empty(P)
    chunk = _points_per_block(chunk, W.shape[0])  # [p, E] intermediates near 4M floats
    for a in range(0, P, chunk):
        phi = features[a : a + chunk] @ W.T  # [p, E]
        i = inverse_norm(phi)  # [p, 1]
        inv[a : a + chunk] = i[:, 0]
        neg[a : a + chunk] = ((phi @ negatives.T) * i).amax(dim=-1)
    return CompositeCache(features.contiguous(), W, inv, neg)


def build_prefix_cache(
    theta: Tensor,  # [P, D] raw theta at the points
    W: Tensor,  # [E, D]
    negatives: Tensor,  # [C, E]
    step: int,  # scales are the prefixes k, 2k, ..., k floor(D / k)
    chunk: int = 65536,
) -> PrefixCache:
    P, D = theta.shape
    dims = supervised_dims(D, step)
    S = len(dims)
    blocks = to_blocks(theta, step)  # [S, k, P]
    gram = W.T @ W  # [D, D]
    negdir = (negatives @ W).T  # [D, C]
    inv = theta.new_empty(S, 1, P)
    neg = theta.new_empty(S, 1, P)
    chunk = _points_per_block(chunk, S * step)
    for a in range(0, P, chunk):
        b = blocks[:, :, a : a + chunk]
        i = inverse_norm_from_sq(prefix_sq_norms(b, gram))  # [S, p]
        inv[:, 0, a : a + chunk] = i
        neg[:, 0, a : a + chunk] = (prefix_dot(b, negdir[: S * step]) * i[:, None, :]).amax(dim=1)
    return PrefixCache(blocks, W, dims, inv, neg, labels=[f"d={d}" for d in dims])


def build_linear_cache(
    theta: Tensor,  # [P, D]
    maps: Tensor,  # [S, E, D]
    negatives: Tensor,  # [C, E]
    labels: Sequence[str],
    chunk: int = 65536,
) -> LinearCache:
    P, D = theta.shape
    S = maps.shape[0]
    grams = torch.einsum("sed,sef->sdf", maps, maps)  # [S, D, D]
    gram_cat = grams.permute(1, 0, 2).reshape(D, S * D)  # [D, S D]
    negdir = torch.einsum("sed,ce->sdc", maps, negatives)  # [S, D, C]
    inv = theta.new_empty(S, 1, P)
    neg = theta.new_empty(S, 1, P)
    chunk = _points_per_block(chunk, S * D)
    for a in range(0, P, chunk):
        t = theta[a : a + chunk]  # [p, D]
        sq = ((t @ gram_cat).view(-1, S, D) * t[:, None, :]).sum(-1).clamp_(min=0.0)  # [p, S]
        i = inverse_norm_from_sq(sq).T  # [S, p]
        inv[:, 0, a : a + chunk] = i
        neg[:, 0, a : a + chunk] = (torch.einsum("pd,sdc->spc", t, negdir) * i[..., None]).amax(-1)
    return LinearCache(theta.contiguous(), maps, inv, neg, labels=list(labels))


def _points_per_block(chunk: int, width: int) -> int:
    """Points per block so that ``[width, points]`` intermediates stay near 4M floats."""
    return max(1, min(chunk, (1 << 22) // max(1, width)))


def select_scale(
    cache: Union[PrefixCache, LinearCache],
    texts: Tensor,  # [Q, E] unit text embeddings
) -> tuple[Tensor, Tensor, Tensor]:  # chosen [Q] int64, scores [Q, S], relevancy [Q, P]
    """Per query, the scale whose highest relevancy over the points is largest (the first such
    scale on a tie, as ``argmax`` picks), that score at every scale, and the relevancy of every
    point at the chosen scale.

    ``sigmoid`` is increasing, so the highest relevancy at a scale is the relevancy of its largest
    margin. A prefix cache (``S = floor(D / k)`` scales) keeps only the ``[S, Q]`` largest margins,
    streamed over the points, and computes the relevancy once, at the chosen scale: no
    ``[S, Q, P]`` relevancy. (With ``k > 1`` the per-block dot products, ``k`` times smaller, come
    from one bmm over all points, so that BLAS rounds them as in the full path.) The 3 levels of
    a linear cache make the ``[S, Q, P]`` margins small: one matmul beats two passes. The scores
    go through the sigmoid before the ``argmax`` (ties where it rounds to 1 included), so the
    choice and the values equal those taken on ``cache.relevancy(texts)``."""
    cols = torch.arange(texts.shape[0], device=texts.device)
    if isinstance(cache, LinearCache):
        margins = cache.margins(texts)  # [S, Q, P]
        scores = _relevancy_of_margins(margins.amax(dim=-1).T.contiguous())  # [Q, S]
        chosen = scores.argmax(dim=1)
        return chosen, scores, _relevancy_of_margins(margins[chosen, cols])
    terms, weights = cache.terms(texts)
    best = prefix_margin_max(terms, weights, cache.inv_norm, cache.neg_max)  # [S, Q]
    scores = _relevancy_of_margins(best.T.contiguous())  # [Q, S]
    chosen = scores.argmax(dim=1)
    at = prefix_margin_at(terms, weights, cache.inv_norm, cache.neg_max, chosen)  # [Q, P]
    return chosen, scores, _relevancy_of_margins(at)


def soft_scales(
    cache: PrefixCache,
    texts: Tensor,  # [Q, E] unit text embeddings
    temperature: float = SOFT_TEMPERATURE,
) -> tuple[Tensor, Tensor]:  # soft relevancy [Q, P], peaks [Q, S]
    """Soft mode (:mod:`n2f2.query.soft`) over a prefix cache's points without its ``[S, Q, P]``
    relevancy: the peaks are the streamed largest margins of :func:`select_scale` through the
    sigmoid; the weighted sum is accumulated over windows of points (``[S, Q, p]`` near 4M
    floats), with the sigmoid taken only at the scales some query weighs at least
    ``NEGLIGIBLE_WEIGHT / S`` (:func:`n2f2.query.soft.weighed_scales`: what is left out adds at
    most 2^-24 to a relevancy). The prefix sums of a window are those of ``cache.relevancy``
    (:func:`prefix_dot`), up to the last scale kept."""
    terms, weights = cache.terms(texts)
    best = prefix_margin_max(terms, weights, cache.inv_norm, cache.neg_max)  # [S, Q]
    peaks = _relevancy_of_margins(best.T.contiguous())  # [Q, S]
    w = soft_weights(peaks, temperature)
    keep = weighed_scales(w)  # [K]
    if len(keep) == 0:  # NaN weights (from a NaN feature): every scale, so that the NaN shows
        keep = torch.arange(w.shape[1], device=w.device)
    last = int(keep[-1]) + 1
    scales: Union[slice, Tensor] = slice(0, last) if len(keep) == last else keep  # a slice copies nothing
    Q, P = texts.shape[0], cache.blocks.shape[2]
    k = cache.blocks.shape[1]
    directions = cache._directions(texts)[: last * k]  # [last k, Q]
    weights_kept = w[:, scales]  # [Q, K]
    out = texts.new_empty(Q, P)
    window = _points_per_block(65536, last * Q)
    for a in range(0, P, window):
        b = min(P, a + window)
        raw = prefix_dot(cache.blocks[:last, :, a:b], directions)[scales]  # [K, Q, p]
        raw.mul_(cache.inv_norm[scales, :, a:b])
        rel = relevancy_from_scores(raw, cache.neg_max[scales, :, a:b], inplace=True)
        out[:, a:b] = soft_combine(rel, weights_kept)
    return out, peaks


_SIGMOID_BLOCK = 16384  # elements per call: one thread (torch's grain is 32768), a multiple of 64


def _relevancy_of_margins(margins: Tensor) -> Tensor:  # [..., P] contiguous, in place -> relevancy
    """``relevancy_from_scores(margins, 0)``. On CPU, in blocks that torch's vectorised sigmoid
    covers whole: its scalar loop for the last few elements of a call can differ in the last bit,
    and the few ``[Q, S]`` maxima would otherwise not take the path of the full tensor's values."""
    flat = margins.view(-1)
    zero = flat.new_zeros(())
    if flat.device.type != "cpu":
        relevancy_from_scores(flat, zero, inplace=True)
        return margins
    n = flat.numel()
    body = n - n % 64
    for a in range(0, body, _SIGMOID_BLOCK):
        relevancy_from_scores(flat[a : min(a + _SIGMOID_BLOCK, body)], zero, inplace=True)
    if body < n:
        tail = flat.new_zeros(64)
        tail[: n - body] = flat[body:]
        flat[body:] = relevancy_from_scores(tail, zero, inplace=True)[: n - body]
    return margins
