"""What a decomposition knows of each node besides its Gaussians: its language embedding, its
size, centroid and box, and the phrase of a vocabulary it matches best.

A node is read where it is whole at its finest: over the field's scales from its last level's
scale up to, not including, the first finer candidate scale that splits it
(:func:`n2f2.hierarchy.build.whole_scales`; ``Decomposition.reads``). At coarser scales of its
span the field already reads it as part of what encloses it (the teacher trained those scales
towards the enclosing segment); at finer ones it reads its parts. Its embedding is the mean of
its Gaussians' unit features over those scales, mapped back to the teacher's space (the
composite embedding of :mod:`n2f2.query.composite`, restricted to the node's own scales)::

    e_k = mean_{i in k} mean_{s} phi_{i,s} / |phi_{i,s}|,   phi_{i,s} = W[:, a_s:b_s] theta_i[a_s:b_s]

so nodes are scored against text by the one relevancy of n2f2 (:mod:`n2f2.field.relevancy`), as
every Gaussian is. Read at its last level's scale alone, node answers scored 4.7 points of mIoU
lower (doubling candidates, two fields of each generated layout; ``docs/measurements.md``, "The
scene's hierarchy"): the tabletop's tea set split at the next candidate (``d = 8``) and, read
at ``d = 4`` alone, matched "table" best; over ``d = 4 .. 7`` it answers "tea set"."""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from ..field.prefix import prefix_sq_norms, to_blocks
from ..field.relevancy import inverse_norm_from_sq, relevancy_margins, relevancy_of_margins
from .build import Decomposition, scale_bases


def scale_inverse_norms(
    theta: Tensor,  # [n, D]
    W: Tensor,  # [E, D]
    scales: list[tuple[int, int]],  # [S] theta dims [start, end) of each scale
) -> Tensor:  # -> [n, S] 1 / max(|phi_s|, eps) of every point at every scale
    """Prefix scales (``start = 0``) all at once from the prefix norms (:func:`prefix_sq_norms`);
    other scales one by one through their Cholesky bases."""
    if all(a == 0 for a, _ in scales):
        top = max(b for _, b in scales)
        Wt = W[:, :top]
        sq = prefix_sq_norms(to_blocks(theta[:, :top], 1), Wt.T @ Wt)  # [top, n]
        return inverse_norm_from_sq(sq[[b - 1 for _, b in scales]].T)
    bases = scale_bases(W, scales)
    sq = [(theta[:, a:b] @ B).square().sum(1) for (a, b), B in zip(scales, bases)]
    return inverse_norm_from_sq(torch.stack(sq, 1))


def node_embeddings(
    theta: Tensor,  # [N, D] the field's features at the Gaussian centres
    W: Tensor,  # [E, D]
    dec: Decomposition,
    chunk: int = 65536,
) -> Tensor:  # -> [K, E] one embedding per node (global id order)
    """``e_k`` of the module docstring. A Gaussian's unit features summed over a node's scales
    are ``W (theta (.) w)`` with ``w = sum_s mask_s / |phi_s|`` (``mask_s`` the scale's dims), so
    nothing ``E``-dimensional is formed per Gaussian."""
    theta = theta.detach().float().cpu()
    W = W.detach().float().cpu()
    K, D = dec.num_nodes, theta.shape[1]
    masks = torch.zeros(len(dec.field_scales), D)  # [S, D]
    for s, (a, b) in enumerate(dec.field_scales):
        masks[s, a:b] = 1.0
    reads = torch.from_numpy(dec.reads)
    sums = torch.zeros(K, D)
    counts = torch.zeros(K)
    for level in range(dec.num_levels):
        col = dec.gaussian_nodes[:, level].astype(np.int64)
        rows = np.flatnonzero((dec.last_levels == level)[col])  # Gaussians of nodes read at this level
        if not len(rows):
            continue
        ends = reads[torch.from_numpy(np.unique(col[rows]))]
        lo, hi = int(ends[:, 0].min()), int(ends[:, 1].max())
        span = torch.arange(lo, hi)
        for i in range(0, len(rows), chunk):
            r = rows[i : i + chunk]
            k = torch.from_numpy(col[r])
            t = theta[torch.from_numpy(r)]
            inv = scale_inverse_norms(t, W, dec.field_scales[lo:hi])  # [n, S']
            inside = (span >= reads[k, 0:1]) & (span < reads[k, 1:2])  # [n, S'] the node's own scales
            sums.index_add_(0, k, t * ((inv * inside) @ masks[lo:hi]))
            counts.index_add_(0, k, inside.sum(1).float())
    return (sums / counts.clamp_min(1)[:, None]) @ W.T


def node_geometry(
    means: np.ndarray,  # [N, 3] Gaussian centres
    dec: Decomposition,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per node: Gaussian count [K], centroid [K, 3], box minimum and maximum [K, 3] each (read
    at each node's first level; it holds the same Gaussians over its span)."""
    K = dec.num_nodes
    counts = np.zeros(K, np.int64)
    sums = np.zeros((K, 3))
    lo = np.full((K, 3), np.inf)
    hi = np.full((K, 3), -np.inf)
    for level in range(dec.num_levels):
        ids = dec.gaussian_nodes[:, level]
        first = dec.levels[ids] == level  # each node once, at its first level
        ids, pts = ids[first], means[first]
        counts += np.bincount(ids, minlength=K)
        for axis in range(3):
            sums[:, axis] += np.bincount(ids, weights=pts[:, axis], minlength=K)
        np.minimum.at(lo, ids, pts)
        np.maximum.at(hi, ids, pts)
    return counts, sums / np.maximum(counts, 1)[:, None], lo, hi


def best_phrases(
    embeddings: Tensor,  # [K, E] node embeddings
    phrases: Sequence[str],
    texts: Tensor,  # [Q, E] unit embeddings of the phrases
    negatives: Tensor,  # [C, E] unit embeddings of the relevancy's negative phrases
) -> tuple[list[Optional[str]], np.ndarray]:
    """Per node the phrase of highest relevancy and that relevancy ([K]); None / NaN without
    phrases. Ranked by the margin (:func:`n2f2.field.relevancy.relevancy_margins`): related
    phrases all reach relevancy 1.0 in float32."""
    K = embeddings.shape[0]
    if not phrases:
        return [None] * K, np.full(K, np.nan)
    margin, best = relevancy_margins(embeddings, texts, negatives).max(dim=1)  # [K]
    rel = relevancy_of_margins(margin)
    return [phrases[int(i)] for i in best], rel.numpy().astype(np.float64)
