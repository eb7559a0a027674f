"""Queries answered by whole nodes of the run's hierarchy (``--mode node``; ``n2f2 decompose``
writes the hierarchy, :mod:`n2f2.hierarchy`).

Each node is scored by the one relevancy of n2f2 (:mod:`n2f2.field.relevancy`) of its embedding,
the mean of its Gaussians' unit features over its own scales (:mod:`n2f2.hierarchy.nodes`). Nodes are
ranked by the relevancy's argument, the margin ``phi^ . t - max_c phi^ . c`` (relevancy is
``sigmoid(10 margin)``, so the order is the same, but the margin does not saturate at 1 in
float32 as the relevancy of related captions does). The answer is the best node, replaced by its
parent for as long as the parent's margin is at least :data:`INSTANCE_SHARE` of the best's (a
patch of a large surface matches "table" as well as the whole table does, and the whole is the
answer), and beside it every node **present at its first level** (a node spans the levels
``level .. last_level``) whose margin is at least :data:`INSTANCE_SHARE` of its own:
instances of one thing (several cookies) were trained towards one teacher embedding, so their
margins match the best's to within the field's noise, while other nodes of that level score
clearly lower. The answer's Gaussians are the
union of its nodes' Gaussians; its 2D map is their rendered coverage (the fraction of each
pixel's colour they give), so the evaluation scores it with the unchanged protocol. A small
second term (:data:`TIE_WEIGHT` times the rendered :func:`gaussian_scores`) orders the pixels
the answer does not cover by their own node's margin at the answer's level, so a ranking metric
(average precision) sees more than the answer's footprint; it stays below any covered pixel's
value, so the protocol's threshold still cuts the coverage."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
from torch import Tensor

from ..cameras import Camera
from ..field.relevancy import relevancy_margins, relevancy_of_margins
from ..hierarchy.build import present

INSTANCE_SHARE = 0.9  # a node joins the answer with >= 90 % of the best node's margin
TIE_WEIGHT = 0.01  # weight of the uncovered pixels' ordering term in a node answer's map


@dataclass
class NodeAnswer:
    """One query's answer: its nodes (the best first), their level, and every node's relevancy."""

    nodes: list[int]  # global node ids, best first
    level: int
    margin: Tensor  # [K] every node's relevancy margin for the query

    @property
    def relevancy(self) -> Tensor:  # [K]
        return relevancy_of_margins(self.margin)

    def level_scores(self, levels: np.ndarray, last_levels: np.ndarray, num_levels: int) -> Tensor:  # -> [L]
        """The best relevancy among the nodes present at each level (a mode's per-scale scores)."""
        rel = self.relevancy
        return torch.stack([rel[torch.from_numpy(present(levels, last_levels, lv))].max() for lv in range(num_levels)])


def choose_nodes(
    margin: Tensor,  # [K] relevancy margin of every node for one query
    levels: np.ndarray,  # [K] each node's first level
    last_levels: np.ndarray,  # [K] each node's last level
    parents: np.ndarray,  # [K] each node's parent, -1 at level 0
) -> NodeAnswer:
    """The best node, raised to its ancestors while they answer as well, and the other instances
    present at its first level (see the module docstring)."""
    best = int(torch.argmax(margin))
    top = float(margin[best])
    if top > 0:  # a piece of a large thing (a patch of the table) gives way to the whole of it
        while parents[best] >= 0 and float(margin[int(parents[best])]) >= INSTANCE_SHARE * top:
            best = int(parents[best])
    level = int(levels[best])
    ref = float(margin[best])
    same = torch.from_numpy(present(levels, last_levels, level))
    keep = same & (margin >= INSTANCE_SHARE * ref) if ref > 0 else torch.zeros_like(same)
    others = [int(k) for k in torch.nonzero(keep).squeeze(1) if int(k) != best]
    others.sort(key=lambda k: -float(margin[k]))
    return NodeAnswer([best, *others], level, margin)


def gaussian_scores(
    gaussian_nodes: np.ndarray,  # [N, L]
    answer: NodeAnswer,
) -> Tensor:  # -> [N] in [0, 1]: each Gaussian's node margin at the answer's level, min-max scaled
    level_nodes = torch.from_numpy(gaussian_nodes[:, answer.level].astype(np.int64))
    m = answer.margin[level_nodes]
    return (m - m.min()) / (m.max() - m.min()).clamp_min(1e-12)


def answer_mask(
    gaussian_nodes: np.ndarray,  # [N, L] node of every Gaussian at every level
    answer: NodeAnswer,
) -> Tensor:  # -> [N] bool, the answer's Gaussians
    return torch.from_numpy(np.isin(gaussian_nodes[:, answer.level], answer.nodes))


@dataclass
class NodeCache:
    """The node mode's score cache: the points are the hierarchy's nodes (their relevancy is
    per node); ``camera`` is the view whose coverage maps are rendered (None over the Gaussians)."""

    embeddings: Tensor  # [K, E] node embeddings
    negatives: Tensor  # [C, E]
    labels: list[str]  # the hierarchy's levels (their scale labels)
    camera: Optional[Camera] = None

    def relevancy(self, texts: Tensor) -> Tensor:  # texts [Q, E] -> [1, Q, K]
        return relevancy_of_margins(self.margins(texts))[None]

    def margins(self, texts: Tensor) -> Tensor:  # texts [Q, E] -> [Q, K]
        return relevancy_margins(self.embeddings, texts, self.negatives).T.contiguous()
