"""THE relevancy score of n2f2: one definition used by every query mode (composite, explicit,
levels, oracle), by 3D queries on Gaussians, and by the evaluation stage.

Relevancy (LERF, Kerr et al. 2023; LangSplat, Qin et al. 2024). For a rendered or per-Gaussian
language feature ``phi``, a text embedding ``t`` and the negative phrases
``c in ("object", "things", "stuff", "texture")``::

    relevancy(phi, t) = min_c softmax(10 * [phi^ . t, phi^ . c])[0]

the smallest probability of the positive over all negatives. Because
``softmax([a, b])[0] = sigmoid(a - b)`` is increasing in ``a - b``, the minimum is reached at the
negative with the largest similarity::

    relevancy(phi, t) = sigmoid(10 * (phi^ . t - max_c phi^ . c))

which is what :func:`relevancy_from_scores` evaluates (tests compare it with the literal
softmax-and-min form).

Feature normalisation (defined here, once). Text embeddings are unit vectors (the encoders
normalise them). Features are L2-normalised before every dot product, as LangSplat's decoder
outputs unit features and LERF normalises its rendered CLIP features: ``phi^ = phi / max(|phi|,
eps)`` with ``eps = 1e-12`` (``torch.nn.functional.normalize``'s rule). So all similarities
are cosines, and a zero feature (an empty pixel, an untrained zero-initialised ``W``) has
similarity 0 with everything and relevancy exactly 0.5. The field itself is never normalised
(paper Sec. 3.2: ``phi`` stays linear in ``theta``); normalisation happens only here, at
scoring time, which is why the fast paths carry ``1 / max(|phi|, eps)`` per pixel or Gaussian.
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

# LERF's negative ("canonical") phrases for relevancy; LangSplat uses the same four.
DEFAULT_NEGATIVES: tuple[str, ...] = ("object", "things", "stuff", "texture")
# Softmax scale of LERF / LangSplat (``10 * [pos, neg]``). Part of the protocol: do not tune.
RELEVANCY_SCALE = 10.0
# Norm floor of the feature normalisation (F.normalize's default).
NORM_EPS = 1e-12


def inverse_norm(features: Tensor) -> Tensor:  # [..., E] -> [..., 1]
    """``1 / max(|phi|, eps)``: the factor that normalises ``phi`` (see module docstring)."""
    return features.norm(dim=-1, keepdim=True).clamp_(min=NORM_EPS).reciprocal_()


def inverse_norm_from_sq(sq_norms: Tensor) -> Tensor:  # [...] -> [...]
    """The same factor from squared norms (fast paths compute ``|phi|^2`` without ``phi``)."""
    return sq_norms.sqrt().clamp_(min=NORM_EPS).reciprocal_()


def normalize_features(features: Tensor) -> Tensor:  # [..., E] -> [..., E]
    """``phi / max(|phi|, eps)``: the one feature normalisation of n2f2."""
    return features * inverse_norm(features)


def relevancy_from_scores(
    positive: Tensor,  # [..., Q] cosine similarities phi^ . t
    negative_max: Tensor,  # [..., 1] or broadcastable: max_c phi^ . c
    inplace: bool = False,  # overwrite ``positive`` (the query fast path owns that buffer)
) -> Tensor:  # [..., Q] relevancy in (0, 1)
    """Relevancy from cosine similarities: ``sigmoid(10 (pos - max_c neg_c))``, which equals
    the minimum over negatives of ``softmax(10 [pos, neg_c])[0]``."""
    if inplace:
        return positive.sub_(negative_max).mul_(RELEVANCY_SCALE).sigmoid_()
    return torch.sigmoid((positive - negative_max) * RELEVANCY_SCALE)


def negative_max(
    features: Tensor,  # [..., E] unnormalised features phi
    negatives: Tensor,  # [C, E] unit text embeddings of the negative phrases
    inv_norm: Tensor | None = None,  # [..., 1] precomputed 1 / max(|phi|, eps)
) -> Tensor:  # [..., 1] max_c phi^ . c
    """The negatives' term of the relevancy, per feature (cached per view by the engine)."""
    if inv_norm is None:
        inv_norm = inverse_norm(features)
    return (features @ negatives.T).mul_(inv_norm).amax(dim=-1, keepdim=True)


def relevancy_margins(
    features: Tensor,  # [..., E] unnormalised language features phi
    texts: Tensor,  # [Q, E] unit text embeddings of the queries
    negatives: Tensor,  # [C, E] unit text embeddings of the negative phrases
) -> Tensor:  # [..., Q] the relevancy's argument phi^ . t - max_c phi^ . c
    """What the relevancy is the sigmoid of (:func:`relevancy_of_margins`). It orders features
    as the relevancy does but does not saturate: related captions reach relevancy 1.0 in float32
    (the hierarchy ranks its nodes and phrases by it)."""
    inv = inverse_norm(features)
    return (features @ texts.T).mul_(inv).sub_(negative_max(features, negatives, inv))


def relevancy_of_margins(margins: Tensor) -> Tensor:  # [...] -> [...] relevancy in (0, 1)
    return torch.sigmoid(margins * RELEVANCY_SCALE)


def relevancy(
    features: Tensor,  # [..., E] unnormalised language features phi (rendered or per Gaussian)
    texts: Tensor,  # [Q, E] unit text embeddings of the queries
    negatives: Tensor,  # [C, E] unit text embeddings of the negative phrases
) -> Tensor:  # [..., Q]
    """Relevancy of every feature for every query (the reference path: normalise, dot, score)."""
    return relevancy_margins(features, texts, negatives).mul_(RELEVANCY_SCALE).sigmoid_()


def check_texts(texts: Sequence[str]) -> list[str]:
    """Validate query strings: at least one, none empty or blank."""
    from ..errors import InputError

    texts = list(texts)
    if not texts:
        raise InputError(None, "no query given: pass at least one text query")
    for t in texts:
        if not isinstance(t, str) or not t.strip():
            raise InputError(None, f"empty query {t!r}: every query needs some text")
    return [t.strip() for t in texts]
