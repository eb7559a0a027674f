"""A class-agnostic hierarchy of the scene's Gaussians read off the trained nested field, with no
text involved: :func:`decompose`.

The field answers, at every scale of its ladder, with a language feature per Gaussian
(``phi_d = W[:, :d] theta[:d]`` for a nested field's prefix ``d``). Gaussians that belong to one
segment at a scale were trained towards one teacher embedding there, so their features agree;
the hierarchy groups them scale by scale:

1. **Candidate scales**: the variant's scales, coarse to fine (:meth:`FieldVariant.coarse_to_fine`),
   thinned to prefix lengths at half-octave steps, ``round(2^(j/2)) k``: 1, 2, 3, 4, 6, 8, 11,
   16, ... (:func:`candidate_scales`). The quantile ladder is uniform in segment-scale rank, and
   neighbouring prefixes differ by one dim, so most of them group alike. Doubling steps (1, 2,
   4, 8, ...) missed groups that are whole only between two of them: over three k-means seeds
   they scored 10.7 points lower on the tabletop's groups (the lounge's: 1.5).
2. **Atoms**: k-means over every candidate scale's unit features at once (:func:`atoms`), so
   that an atom is pure at every scale; nodes are unions of atoms, which is what makes nesting
   hold by construction.
3. **Levels, fine to coarse** (:func:`group_scales`): at each candidate scale, the clusters of the
   finer scale (atoms at the finest) are merged by average linkage on their mean feature at this
   scale, cut at cosine distance ``2 delta``. ``delta`` is the field's own scatter at that scale:
   the median plus 3 scaled MADs (the robust outlier rule of segment lifting) of each
   Gaussian's cosine distance to its cluster's mean; two members of one segment can lie up to
   twice that apart. No constant is tuned on a scene.
4. **Splinters** (:func:`absorb_splinters`), coarse to fine: a cluster is a node only where it is
   a piece of space of its own: for most of its Gaussians (more than half), the nearest of
   their parent's Gaussians is in it. A part, an object or each instance of one (a cookie)
   is; Gaussians that stray from a surface's feature at one scale are interleaved with the rest
   of it and join the sibling whose mean feature is nearest. Left alone, such splinters made a
   large surface lose a few Gaussians at every level (the demo's table: 4,660, 4,615, 4,498)
   and show as near-identical nodes that a view's best match flips between. Positions are used
   for this test only: they never split nor join anything on their own.
5. **Level choice** (:func:`choose_levels`): candidates that group alike (the same number of
   nodes as the next coarser one) are dropped, and of the rest at most ``max_levels`` are kept
   where the grouping changes most: the largest ratios of node counts between a candidate and
   the next coarser one.
6. **Node ids** (:func:`node_ids`): a node is a set of Gaussians. Where a node of one level is
   not split at the next finer one, the finer level holds the same node (the same id): a node
   spans the levels ``level .. last_level``.
7. **Reads** (:func:`whole_scales`): per node, the field's scales at which it is whole at its
   finest, from its last level's scale up to the first finer candidate that splits it; its
   embedding is read over them (:mod:`.nodes`).

Nodes carry global ids, coarsest first; ``gaussian_nodes [N, L]`` gives every Gaussian's node at
every level, and each node's parent is the node of the level above its first one that holds its
Gaussians (the same for all of them, by construction).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Optional

import numpy as np
import torch
from torch import Tensor

from ..config import option
from ..validate import nonneg_int, positive_int

if TYPE_CHECKING:
    from ..field.variants import FieldVariant


@dataclass(frozen=True)
class DecomposeConfig:
    """Settings of :func:`decompose` (``n2f2 decompose``'s options)."""

    max_levels: int = option(
        6, help="at most this many levels, kept where the grouping changes most", type=positive_int, metavar="L"
    )
    candidates_per_octave: int = option(
        2,
        help="candidate prefix lengths per doubling of the prefix (1: d = 1, 2, 4, 8, ...)",
        type=positive_int,
        metavar="C",
    )
    atoms_per_gaussian: float = 1 / 12  # k-means atoms: N / 12 ...
    max_atoms: int = 2048  # ... at most this many (average linkage is quadratic in them)
    min_atoms: int = 16
    kmeans_sample: int = 131072  # k-means is fitted on at most this many Gaussians, then all are assigned
    kmeans_iterations: int = 25
    basis_dims: int = 64  # the atoms' k-means runs on this many principal components of the features
    noise_mads: float = 3.0  # delta = median + noise_mads * 1.4826 * MAD (segment lifting's rule)
    seed: int = option(
        0,
        help="seed of the k-means atoms (the tree varies with it: docs/measurements.md)",
        type=nonneg_int,
        metavar="S",
    )
    chunk: int = 65536  # Gaussians per block when reading features


@dataclass
class Decomposition:
    """A hierarchy of Gaussians: ``L`` levels, coarsest first."""

    gaussian_nodes: np.ndarray  # [N, L] int32 global node id of every Gaussian at every level
    level_scales: list[tuple[int, int]]  # [L] theta dims [start, end) each level's features read
    level_labels: list[str]  # [L] the field's names of those scales ("d=16")
    level_values: list[float]  # [L] quantized scale s in [0, 1) at the middle of each level's bin
    parents: np.ndarray  # [K] int64 parent node id, -1 at level 0
    levels: np.ndarray  # [K] int64 first (coarsest) level of each node
    last_levels: np.ndarray  # [K] int64 last (finest) level each node spans, unsplit
    thresholds: list[float]  # [L] the cosine distance each level was cut at (2 delta)
    field_scales: list[tuple[int, int]]  # [S] theta dims [start, end) of every scale of the field, coarse to fine
    field_labels: list[str]  # [S] their names
    reads: np.ndarray  # [K, 2] int64 [first, end) indices into field_scales: where each node is read (whole_scales)
    candidates: list[dict] = field(default_factory=list)  # every candidate scale: label, nodes, kept

    @property
    def num_levels(self) -> int:
        return int(self.gaussian_nodes.shape[1])

    @property
    def num_nodes(self) -> int:
        return int(self.parents.shape[0])

    def nodes_at(self, level: int) -> np.ndarray:  # -> [K_l] node ids
        """The nodes present at ``level`` (the ids of its column of ``gaussian_nodes``)."""
        return np.nonzero(present(self.levels, self.last_levels, level))[0]


def present(
    levels: np.ndarray,  # [K] each node's first level
    last_levels: np.ndarray,  # [K] each node's last level
    level: int,
) -> np.ndarray:  # -> [K] bool, the nodes of that level's column of gaussian_nodes
    return (levels <= level) & (level <= last_levels)


def candidate_scales(variant: "FieldVariant", dim: int, step_size: int, per_octave: int = 2) -> list[int]:
    """Indices into ``variant.coarse_to_fine(dim, step_size)`` of the candidate scales: prefix
    lengths ``round(2^(j / per_octave))`` scales long (every scale when there are at most 8), the
    finest always included."""
    n = len(variant.coarse_to_fine(dim, step_size))
    if n <= 8:
        return list(range(n))
    steps = int(np.ceil(per_octave * np.log2(n)))
    return sorted({min(n, round(2 ** (j / per_octave))) - 1 for j in range(steps + 1)})


def scale_bases(W: Tensor, scales: list[tuple[int, int]]) -> list[Tensor]:  # W [E, D] -> [d, d] each
    """Per scale ``[a, b)`` a matrix ``B`` with ``(theta B) . (theta' B) = phi . phi'`` for
    ``phi = W[:, a:b] theta[a:b]``: the Cholesky factor of ``W[:, a:b]^T W[:, a:b]`` (plus a
    tiny ridge), so cosines are computed in ``b - a`` dims instead of E."""
    out = []
    for a, b in scales:
        Wd = W[:, a:b].double()
        G = Wd.T @ Wd
        ridge = 1e-10 * float(G.diagonal().mean().clamp_min(1e-30))
        L = torch.linalg.cholesky(G + ridge * torch.eye(b - a, dtype=G.dtype))
        out.append(L.float())  # (theta L) . (theta' L) = theta G theta'
    return out


def unit_features(
    theta: Tensor,  # [n, D]
    scale: tuple[int, int],
    basis: Tensor,  # [d, d] from scale_bases
) -> Tensor:  # -> [n, d] unit rows (zero where the feature is zero)
    a, b = scale
    z = theta[:, a:b] @ basis
    return z / z.norm(dim=1, keepdim=True).clamp_min(1e-12)


def kmeans_pp(
    points: Tensor,  # [n, q]
    num: int,
    gen: torch.Generator,
) -> Tensor:  # -> [num] int64 indices of the initial centres
    """k-means++ seeding (Arthur and Vassilvitskii, 2007): each next centre is a point drawn with
    probability proportional to its squared distance to the nearest centre so far, so that no
    region of feature space is left without a centre (random points from the sample seeded
    small surfaces and parts poorly: lounge parts 74.1 against 76.0, three k-means seeds)."""
    sq = points.square().sum(1)  # [n]

    def dist2(i: int) -> Tensor:  # [n] squared distances to point i, |p|^2 - 2 p.c + |c|^2 (a matvec)
        return (sq - 2.0 * (points @ points[i]) + sq[i]).clamp_min_(0.0)

    first = int(torch.randint(points.shape[0], (1,), generator=gen))
    picked = [first]
    d2 = dist2(first)  # [n] squared distance to the nearest centre
    for _ in range(num - 1):
        i = int(torch.multinomial(d2 + 1e-30, 1, generator=gen))
        picked.append(i)
        d2 = torch.minimum(d2, dist2(i))
    return torch.tensor(picked, dtype=torch.long)


def atoms(
    theta: Tensor,  # [N, D]
    scales: list[tuple[int, int]],
    bases: list[Tensor],
    config: DecomposeConfig,
) -> np.ndarray:  # -> [N] int64 atom of each Gaussian, 0..A-1
    """k-means over the concatenated unit features of every candidate scale (each scale weighted
    equally), on ``basis_dims`` principal components, seeded by :func:`kmeans_pp`; fitted on a
    sample, then all assigned."""
    n = theta.shape[0]
    num = int(np.clip(round(n * config.atoms_per_gaussian), config.min_atoms, config.max_atoms))
    num = min(num, n)
    gen = torch.Generator().manual_seed(config.seed)
    w = 1.0 / np.sqrt(len(scales))

    def stacked(rows: Tensor) -> Tensor:  # [m, D] -> [m, sum d]
        return torch.cat([unit_features(rows, s, B) * w for s, B in zip(scales, bases)], dim=1)

    sample = torch.randperm(n, generator=gen)[: min(n, config.kmeans_sample)]
    X = stacked(theta[sample])
    q = min(config.basis_dims, X.shape[1], X.shape[0])
    mean = X.mean(0)
    _, _, V = torch.linalg.svd(X - mean, full_matrices=False)
    P = V[:q].T  # [sum d, q]
    Y = (X - mean) @ P
    centres = Y[kmeans_pp(Y, num, gen)].clone()
    for _ in range(config.kmeans_iterations):
        assign = torch.cdist(Y, centres).argmin(1)
        sums = torch.zeros_like(centres).index_add_(0, assign, Y)
        counts = torch.bincount(assign, minlength=num).float()
        filled = counts > 0
        centres[filled] = sums[filled] / counts[filled, None]
    out = torch.empty(n, dtype=torch.long)
    for i in range(0, n, config.chunk):
        Yi = (stacked(theta[i : i + config.chunk]) - mean) @ P
        out[i : i + config.chunk] = torch.cdist(Yi, centres).argmin(1)
    return np.unique(out.numpy(), return_inverse=True)[1].astype(np.int64)


def cluster_means(
    theta: Tensor,  # [N, D]
    labels: np.ndarray,  # [N] cluster 0..C-1
    scale: tuple[int, int],
    basis: Tensor,  # [d, d]
    chunk: int,
) -> tuple[Tensor, Tensor]:  # -> unit mean [C, d], each Gaussian's cosine distance to it [N]
    C = int(labels.max()) + 1
    lab = torch.from_numpy(labels)
    sums = torch.zeros(C, basis.shape[1])
    for i in range(0, theta.shape[0], chunk):
        sums.index_add_(0, lab[i : i + chunk], unit_features(theta[i : i + chunk], scale, basis))
    means = sums / sums.norm(dim=1, keepdim=True).clamp_min(1e-12)
    dist = torch.empty(theta.shape[0])
    for i in range(0, theta.shape[0], chunk):
        z = unit_features(theta[i : i + chunk], scale, basis)
        dist[i : i + chunk] = 1.0 - (z * means[lab[i : i + chunk]]).sum(1)
    return means, dist


def scatter(dist: Tensor, mads: float) -> float:  # dist [N] -> delta
    """Median plus ``mads`` scaled median absolute deviations of the cosine distances."""
    d = dist.double()
    med = d.median()
    return float(med + mads * 1.4826 * (d - med).abs().median())


def merge_clusters(means: Tensor, cut: float) -> np.ndarray:  # means [C, d] unit -> [C] new label
    """Average linkage on cosine distance, cut at ``cut``."""
    from scipy.cluster.hierarchy import fcluster, linkage

    if means.shape[0] < 2:
        return np.zeros(means.shape[0], dtype=np.int64)
    Z = linkage(means.double().numpy(), method="average", metric="cosine")
    return (fcluster(Z, t=cut, criterion="distance") - 1).astype(np.int64)


def group_scales(
    theta: Tensor,  # [N, D]
    scales: list[tuple[int, int]],  # coarse to fine
    bases: list[Tensor],
    atom_of: np.ndarray,  # [N] atoms
    config: DecomposeConfig,
) -> tuple[list[np.ndarray], list[float]]:
    """One partition per scale, coarse to fine, each nested in the next coarser (clusters of a
    finer scale are merged whole), and the cut of each."""
    current = atom_of
    parts: list[np.ndarray] = []
    cuts: list[float] = []
    for scale, basis in zip(reversed(scales), reversed(bases)):
        means, dist = cluster_means(theta, current, scale, basis, config.chunk)
        cut = 2.0 * scatter(dist, config.noise_mads)
        current = merge_clusters(means, cut)[current]
        parts.append(current)
        cuts.append(cut)
    return parts[::-1], cuts[::-1]


def own_shares(
    means: np.ndarray,  # [n, 3] the centres of one parent's Gaussians
    labels: np.ndarray,  # [n] their cluster 0..C-1
) -> np.ndarray:  # -> [C] each cluster's share of Gaussians whose nearest neighbour is in it
    """Per cluster, the share of its Gaussians whose nearest other Gaussian (of these) is in the
    same cluster: near 1 for a compact piece, near its size share for one scattered among the
    others."""
    from scipy.spatial import KDTree

    C = int(labels.max()) + 1
    if len(labels) < 2:
        return np.ones(C)
    nn = np.asarray(KDTree(means).query(means, k=2)[1])  # [n, 2] the point itself and its nearest
    me = np.arange(len(labels))
    other = np.where(nn[:, 1] == me, nn[:, 0], nn[:, 1])  # a duplicate centre may come first
    same = labels[other] == labels
    return np.bincount(labels, weights=same.astype(np.float64), minlength=C) / np.bincount(labels, minlength=C)


def absorb_splinters(
    theta: Tensor,  # [N, D]
    means: np.ndarray,  # [N, 3] Gaussian centres
    parts: list[np.ndarray],  # [S] of [N] cluster labels, coarse to fine, each nested in the previous
    scales: list[tuple[int, int]],
    bases: list[Tensor],
    chunk: int,
) -> list[np.ndarray]:  # [S] of [N], still nested
    """Coarse to fine, every cluster that is not its own piece of space (:func:`own_shares` of at
    most one half among its parent's Gaussians) joins its sibling of nearest mean feature at this
    scale that is; siblings none of which is become one cluster. Nesting holds: a cluster only
    takes a sibling's label, and the clusters of finer scales inside a joined splinter now lie
    inside the sibling."""
    out: list[np.ndarray] = []
    for labels, scale, basis in zip(parts, scales, bases):
        ids, local = np.unique(labels, return_inverse=True)
        up = out[-1] if out else np.zeros_like(labels)  # the (absorbed) coarser partition
        parent = np.zeros(len(ids), dtype=np.int64)
        parent[local] = up
        target = np.arange(len(ids))
        feats: Optional[Tensor] = None
        for p in np.unique(parent):
            family = np.flatnonzero(parent == p)
            if len(family) < 2:
                continue
            members = np.flatnonzero(up == p)
            rank = np.searchsorted(family, local[members])  # 0..len(family)-1
            own = own_shares(means[members], rank) > 0.5  # a majority
            if own.all():
                continue
            if not own.any():  # no sibling is a piece of its own: they are one cluster
                target[family] = family[0]
                continue
            if feats is None:
                feats = cluster_means(theta, local, scale, basis, chunk)[0]
            stray, kept = family[~own], family[own]
            target[stray] = kept[(feats[stray] @ feats[kept].T).argmax(1).numpy()]
        out.append(target[local])
    return out


def node_ids(
    kept: list[np.ndarray],  # [L] of [N] cluster labels, coarse to fine, nested
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Global node ids, coarsest first: a cluster with the same Gaussians as its parent (its
    parent's only child) keeps the parent's id. Returns ``gaussian_nodes [N, L]`` int32 and per
    node its parent, first level and last level ``[K]`` int64."""
    n = kept[0].shape[0]
    nodes = np.empty((n, len(kept)), dtype=np.int32)
    parents: list[int] = []
    first: list[int] = []
    last: list[int] = []
    for level, labels in enumerate(kept):
        local = np.unique(labels, return_inverse=True)[1]
        k = int(local.max()) + 1
        ids = np.empty(k, dtype=np.int64)
        if level:
            up = np.empty(k, dtype=np.int64)
            up[local] = nodes[:, level - 1]  # every member agrees (nested)
            children = np.bincount(up, minlength=len(parents))
        for c in range(k):
            if level and children[up[c]] == 1:  # unsplit: the same node one level further
                ids[c] = up[c]
                last[up[c]] = level
            else:
                ids[c] = len(parents)
                parents.append(int(up[c]) if level else -1)
                first.append(level)
                last.append(level)
        nodes[:, level] = ids[local]
    return nodes, np.array(parents, dtype=np.int64), np.array(first, dtype=np.int64), np.array(last, dtype=np.int64)


def whole_scales(
    parts: list[np.ndarray],  # [C] of [N] candidate partitions, coarse to fine, nested
    picked: list[int],  # [C] each candidate's index among the field's scales
    kept: list[int],  # [L] the candidates kept as levels
    nodes: np.ndarray,  # [N, L] global node ids
    last: np.ndarray,  # [K] each node's last level
    num_scales: int,  # S, the field's scales
) -> np.ndarray:  # -> [K, 2] int64 [first, end) field scale indices
    """Per node, the field's scales at which it is whole at its finest: from its last level's
    scale up to, not including, the first finer candidate that splits its Gaussians (to the
    field's finest scale when none does). Its embedding is read over them (:mod:`.nodes`)."""
    out = np.zeros((last.shape[0], 2), dtype=np.int64)
    for level, first in enumerate(kept):
        waiting = last == level  # [K] nodes whose end is not found yet
        out[waiting] = (picked[first], num_scales)
        col = nodes[:, level].astype(np.int64)
        for c in range(first + 1, len(parts)):
            if not waiting.any():
                break
            width = int(parts[c].max()) + 1
            pairs = np.unique(col * width + parts[c])  # the (node, cluster) pairs present
            split = np.bincount(pairs // width, minlength=last.shape[0]) > 1
            out[waiting & split, 1] = picked[c]
            waiting &= ~split
    return out


def choose_levels(counts: list[int], max_levels: int) -> list[int]:
    """Indices (coarse to fine) of the candidates kept as levels: one candidate per distinct
    grouping (the finest of equal counts: nested partitions with as many nodes are equal), no
    single-node level when another exists, and at most ``max_levels`` of those whose count grows
    most over the next coarser distinct one."""
    distinct = [i for i in range(len(counts)) if i + 1 == len(counts) or counts[i + 1] != counts[i]]
    many = [i for i in distinct if counts[i] > 1] or distinct[-1:]
    if len(many) <= max_levels:
        return many
    growth = {i: counts[i] / (counts[many[j - 1]] if j else 1) for j, i in enumerate(many)}
    return sorted(sorted(many, key=lambda i: -growth[i])[:max_levels])


def decompose(
    theta: Tensor,  # [N, D] the field's features at the Gaussian centres
    means: Tensor,  # [N, 3] the Gaussian centres
    W: Tensor,  # [E, D] the field's projection
    variant: "FieldVariant",
    step_size: int,
    config: Optional[DecomposeConfig] = None,
) -> Decomposition:
    """The hierarchy of the Gaussians (see the module docstring)."""
    config = config or DecomposeConfig()
    theta = theta.detach().float().cpu()
    W = W.detach().float().cpu()
    dim = theta.shape[1]
    all_scales = variant.coarse_to_fine(dim, step_size)
    labels = variant.coarse_to_fine_labels(dim, step_size)
    values = variant.coarse_to_fine_values(dim, step_size)
    picked = candidate_scales(variant, dim, step_size, config.candidates_per_octave)
    scales = [all_scales[i] for i in picked]
    bases = scale_bases(W, scales)
    atom_of = atoms(theta, scales, bases, config)
    parts, cuts = group_scales(theta, scales, bases, atom_of, config)
    parts = absorb_splinters(theta, means.detach().double().cpu().numpy(), parts, scales, bases, config.chunk)
    counts = [int(np.unique(p).shape[0]) for p in parts]
    kept = choose_levels(counts, config.max_levels)
    nodes, parents, first, last = node_ids([parts[i] for i in kept])
    reads = whole_scales(parts, picked, kept, nodes, last, len(all_scales))
    return Decomposition(
        gaussian_nodes=nodes,
        level_scales=[scales[i] for i in kept],
        level_labels=[labels[picked[i]] for i in kept],
        level_values=[values[picked[i]] for i in kept],
        parents=parents,
        levels=first,
        last_levels=last,
        thresholds=[cuts[i] for i in kept],
        field_scales=list(all_scales),
        field_labels=list(labels),
        reads=reads,
        candidates=[
            {"scale_label": labels[picked[i]], "nodes": counts[i], "cut": cuts[i], "kept": i in kept}
            for i in range(len(picked))
        ],
    )
