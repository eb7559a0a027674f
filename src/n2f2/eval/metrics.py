"""Retrieval and comparison metrics around the protocols.

* **R@K over a segment pool.** Each segment (a region id of a view, or a bank segment) is
  scored by the mean relevancy over its pixels; segments are ranked by that score, per query.
  A query's positives are the segments it refers to.

  - rank of a segment = the number of pool segments scoring at least as high as it (itself
    included): ties count *against* the query, so a constant relevancy map retrieves nothing
    (rank = pool size) rather than whatever the input order happens to favour.
  - ``recall@K = |positives with rank <= K| / min(K, |positives|)``: 1 when the top K are all
    positives (or hold all of them), and the usual hit@K for a single positive.
  - positives that are not in the pool (absent from the view) are left out; a query with no
    positive in the pool is listed in ``skipped`` and not averaged.

  To pool segments over several views, score each view with :func:`segment_mean_relevancy`
  and concatenate the columns (ids then index the concatenation).

* **Average precision (AP) of a relevancy map.** The pixels of a frame are ranked by relevancy
  against a ground-truth mask (threshold-free: it separates ranking the right pixels first from
  the protocol's min-max threshold). Defined as scikit-learn's ``average_precision_score``:
  ``AP = sum_n (R_n - R_{n-1}) P_n`` over the distinct scores taken as thresholds, highest
  first (``P_n``, ``R_n``: precision and recall of the pixels scoring at least the n-th
  threshold, ``R_0 = 0``). Tied scores form one threshold, so pixels of equal relevancy are
  counted together, whatever their order. A map constant over the image scores the mask's
  share of the pixels.

* **Per-query deltas between two runs** (e.g. N2F2 against a baseline): ``delta = b - a`` for
  every query both runs scored, sorted, with the top and bottom ``n``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Mapping, Optional, Sequence

import numpy as np


def segment_mean_relevancy(
    relevancy: np.ndarray,  # [Q, H, W] or [H, W] relevancy per query
    segments: np.ndarray,  # [L, H, W] or [H, W] int segment id per pixel and layer, -1 = none
    num_segments: Optional[int] = None,  # pool size S; default max id + 1
) -> tuple[np.ndarray, np.ndarray]:  # mean relevancy [Q, S] (NaN if absent), areas [S] int64
    """Mean relevancy of every segment, per query. A pixel counts for every layer's segment it
    belongs to (nested levels: part, object, group)."""
    rel = np.asarray(relevancy, dtype=np.float64)
    single = rel.ndim == 2
    if single:
        rel = rel[None]
    seg = np.asarray(segments)
    if seg.ndim == 2:
        seg = seg[None]
    if rel.ndim != 3 or seg.ndim != 3 or rel.shape[1:] != seg.shape[1:]:
        raise ValueError(
            f"relevancy [Q, H, W] {np.shape(relevancy)} and segments [L, H, W] {np.shape(segments)} must share H, W"
        )
    if not np.issubdtype(seg.dtype, np.integer):
        raise ValueError(f"segment ids must be integers, got {seg.dtype}")
    if seg.min(initial=-1) < -1:
        raise ValueError("segment ids must be >= 0, or -1 for none")
    s = int(seg.max(initial=-1)) + 1 if num_segments is None else int(num_segments)
    if seg.max(initial=-1) >= s:
        raise ValueError(f"segment id {int(seg.max())} is outside the pool of {s}")
    areas = np.zeros(s, dtype=np.int64)
    sums = np.zeros((len(rel), s), dtype=np.float64)
    for layer in seg:
        valid = layer >= 0
        ids = layer[valid]
        areas += np.bincount(ids, minlength=s)
        for q in range(len(rel)):
            sums[q] += np.bincount(ids, weights=rel[q][valid], minlength=s)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(areas > 0, sums / np.maximum(areas, 1), np.nan)
    return (means[0] if single else means), areas


def segment_ranks(
    scores: np.ndarray,  # [S] segment scores, NaN = not in the pool
) -> np.ndarray:  # [S] float: rank (1 = best, ties pessimistic), NaN outside the pool
    """Rank of each pool segment: how many pool segments score at least as high."""
    s = np.asarray(scores, dtype=np.float64)
    valid = ~np.isnan(s)
    pool = np.sort(s[valid])
    ranks = np.full(s.shape, np.nan)
    # segments with score >= x = pool size - (segments with score < x)
    ranks[valid] = len(pool) - np.searchsorted(pool, s[valid], side="left")
    return ranks


@dataclass
class QueryRetrieval:
    query: str
    first_rank: int  # best rank among the positives in the pool
    recall: dict[int, float]  # K -> recall@K
    num_positives: int  # positives in the pool


@dataclass
class RetrievalScores:
    ks: list[int]
    recall: dict[int, float]  # K -> mean recall@K over scored queries
    mean_first_rank: float
    per_query: list[QueryRetrieval]
    skipped: list[str] = field(default_factory=list)  # queries with no positive in the pool
    pool_size: int = 0

    def to_dict(self) -> dict:
        return asdict(self)


def recall_at_k(
    scores: np.ndarray,  # [Q, S] per-query segment scores (NaN = not in the pool)
    positives: Sequence[Sequence[int]],  # per query, the segment ids it refers to
    ks: Sequence[int] = (1, 3, 5),
    queries: Optional[Sequence[str]] = None,  # names for the report; default "q0", "q1", ...
) -> RetrievalScores:
    """R@K of each query over the pool, and the mean over queries (see module docstring)."""
    sc = np.asarray(scores, dtype=np.float64)
    if sc.ndim != 2:
        raise ValueError(f"scores must be [Q, S], got shape {sc.shape}")
    if len(positives) != len(sc):
        raise ValueError(f"{len(sc)} score rows but {len(positives)} positive lists")
    ks = sorted({int(k) for k in ks})
    if not ks or ks[0] < 1:
        raise ValueError(f"K values must be >= 1, got {ks}")
    names = list(queries) if queries is not None else [f"q{i}" for i in range(len(sc))]
    if len(names) != len(sc):
        raise ValueError(f"{len(sc)} score rows but {len(names)} query names")
    per_query: list[QueryRetrieval] = []
    skipped: list[str] = []
    for q in range(len(sc)):
        ids = np.unique(np.asarray(positives[q], dtype=np.int64))
        if ids.size and (ids.min() < 0 or ids.max() >= sc.shape[1]):
            raise ValueError(f"query {names[q]!r}: positive ids {ids.tolist()} outside the pool of {sc.shape[1]}")
        ranks = segment_ranks(sc[q])[ids]
        ranks = ranks[~np.isnan(ranks)]
        if ranks.size == 0:
            skipped.append(names[q])
            continue
        rec = {k: float((ranks <= k).sum() / min(k, ranks.size)) for k in ks}
        per_query.append(QueryRetrieval(names[q], int(ranks.min()), rec, int(ranks.size)))
    mean = {k: (float(np.mean([p.recall[k] for p in per_query])) if per_query else math.nan) for k in ks}
    first = float(np.mean([p.first_rank for p in per_query])) if per_query else math.nan
    pool = int((~np.isnan(sc)).any(axis=0).sum())
    return RetrievalScores(ks, mean, first, per_query, skipped, pool)


# ------------------------------------------------------------------------------ AP
def average_precision(
    scores: np.ndarray,  # [...] relevancy (or any score), higher = more likely positive
    positives: np.ndarray,  # [...] bool ground truth, same shape, at least one True
) -> float:
    """Average precision of ranking ``scores`` against ``positives`` (see module docstring;
    equal to scikit-learn's ``average_precision_score``, ties as one threshold)."""
    s = np.asarray(scores).reshape(-1)
    if not np.issubdtype(s.dtype, np.floating):
        s = s.astype(np.float64)
    y = np.asarray(positives).reshape(-1) != 0
    if np.shape(scores) != np.shape(positives):
        raise ValueError(f"scores {np.shape(scores)} and positives {np.shape(positives)} differ in shape")
    if not np.isfinite(s).all():
        raise ValueError("scores contain NaN or infinite values")
    total = int(y.sum())
    if total == 0:
        raise ValueError("average precision needs at least one positive")
    # Recall changes only at thresholds equal to a positive's score: at each distinct positive
    # score v (highest first), tp = positives scoring >= v and n = all scoring >= v, counted by
    # binary search in the sorted scores (no argsort: a tie group's order does not matter).
    positive = np.sort(s[y])
    thresholds = np.unique(positive)[::-1]  # distinct positive scores, highest first
    tp = (total - np.searchsorted(positive, thresholds, side="left")).astype(np.float64)
    n = (s.size - np.searchsorted(np.sort(s), thresholds, side="left")).astype(np.float64)
    return float(np.sum(np.diff(tp / total, prepend=0.0) * (tp / n)))


# ------------------------------------------------------------------------------ deltas
@dataclass
class QueryDelta:
    query: str
    a: float
    b: float
    delta: float  # b - a


@dataclass
class QueryDeltas:
    deltas: list[QueryDelta]  # every shared query, largest delta first
    top: list[QueryDelta]  # the n largest deltas, largest first
    bottom: list[QueryDelta]  # the n smallest deltas, smallest first (overlap top if < 2n queries)
    mean_delta: float
    only_a: list[str] = field(default_factory=list)
    only_b: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)


def query_deltas(
    run_a: Mapping[str, float],  # query -> score of the reference run
    run_b: Mapping[str, float],  # query -> score of the compared run
    n: int = 3,
) -> QueryDeltas:
    """Per-query ``b - a`` over the queries both runs scored; ties keep the query-name order."""
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    for name, run in (("a", run_a), ("b", run_b)):
        bad = [q for q, v in run.items() if not np.isfinite(v)]
        if bad:
            raise ValueError(f"run {name} has non-finite scores for {bad[:3]}")
    shared = sorted(set(run_a) & set(run_b))
    deltas = [QueryDelta(q, float(run_a[q]), float(run_b[q]), float(run_b[q]) - float(run_a[q])) for q in shared]
    ordered = sorted(deltas, key=lambda d: -d.delta)  # stable: name order among ties
    worst = sorted(deltas, key=lambda d: d.delta)
    return QueryDeltas(
        deltas=ordered,
        top=ordered[:n],
        bottom=worst[:n],
        mean_delta=float(np.mean([d.delta for d in deltas])) if deltas else math.nan,
        only_a=sorted(set(run_a) - set(run_b)),
        only_b=sorted(set(run_b) - set(run_a)),
    )


def per_query_scores(
    pairs: Sequence,  # protocol.PairRecord list (SceneScores.pairs)
    metric: str = "iou",  # "iou" or "hit"
) -> dict[str, float]:
    """Mean of a pair metric per category (query) over the frames it is labelled in."""
    if metric not in ("iou", "hit"):
        raise ValueError(f"metric must be 'iou' or 'hit', got {metric!r}")
    acc: dict[str, list[float]] = {}
    for p in pairs:
        acc.setdefault(p.category, []).append(float(getattr(p, metric)))
    return {q: float(np.mean(v)) for q, v in acc.items()}
