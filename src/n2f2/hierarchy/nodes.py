"""What a decomposition knows of each node besides its Gaussians: its language embedding at its
own scale, its size, centroid and box, and the phrase of a vocabulary it matches best.

A node's own scale is that of its last (finest) level: the finest scale at which it is still
whole. At coarser scales of its span the field already reads it as part of what encloses it
(the teacher trained those scales towards the enclosing segment).

A node's embedding is the mean of its Gaussians' unit features at the level's scale, mapped
back to the teacher's space: ``mean_i(phi_i / |phi_i|) = W[:, a:b] mean_i(theta_i[a:b] / |phi_i|)``
(``phi_i = W[:, a:b] theta_i[a:b]``), so nodes are scored against text by the one relevancy of
n2f2 (:mod:`n2f2.field.relevancy`), as every Gaussian is."""

from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from ..field.relevancy import relevancy_margins, relevancy_of_margins
from .build import Decomposition, scale_bases


def node_embeddings(
    theta: Tensor,  # [N, D] the field's features at the Gaussian centres
    W: Tensor,  # [E, D]
    dec: Decomposition,
    chunk: int = 65536,
) -> Tensor:  # -> [K, E] one embedding per node (global id order)
    theta = theta.detach().float().cpu()
    W = W.detach().float().cpu()
    out = torch.zeros(dec.num_nodes, W.shape[0])
    for level, ((a, b), basis) in enumerate(zip(dec.level_scales, scale_bases(W, dec.level_scales))):
        ids = torch.from_numpy(dec.gaussian_nodes[:, level].astype(np.int64))
        sums = torch.zeros(dec.num_nodes, b - a)
        for i in range(0, theta.shape[0], chunk):
            t = theta[i : i + chunk, a:b]
            inv = 1.0 / (t @ basis).norm(dim=1, keepdim=True).clamp_min(1e-12)  # 1 / |phi_i|
            sums.index_add_(0, ids[i : i + chunk], t * inv)
        counts = torch.bincount(ids, minlength=dec.num_nodes).clamp_min(1).float()
        mine = torch.from_numpy(np.nonzero(dec.last_levels == level)[0])  # read at its last level
        out[mine] = (sums[mine] / counts[mine, None]) @ W[:, a:b].T
    return out


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
