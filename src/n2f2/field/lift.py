"""``lift``: training-free per-Gaussian features at the segment bank's 3 levels (Occam's LGS).

Each Gaussian ``g`` gets, at each level ``l`` (0 = part, 1 = object, 2 = group), the
blending-weight-weighted average of the teacher's 2D features of the pixels it renders into,
over all training views, in one pass::

    f_{g,l} = sum_{v, p} w_{v,p,g} e_l(v, p) / sum_{v, p} w_{v,p,g} [p covered at level l]

normalised to unit length per Gaussian and level (zero where the Gaussian renders into no
covered pixel). ``w_{v,p,g} = alpha_g(p) T_g(p)`` are the rasterizer's blending weights, the
sparse per-pixel (Gaussian, weight) lists that the trainer caches (:mod:`n2f2.train.blend`),
and ``e_l(v, p)`` is the embedding of the bank segment covering pixel ``p`` at level ``l``
(:func:`level_segments`). Pixels are grouped by segment first, so the work is one weighted
count of (Gaussian, segment) pairs per view and one sparse product with the embeddings.

The result is queried as the 3-level baseline field is (``levels`` and ``oracle`` modes of
:class:`n2f2.query.lifted.LiftEngine`): the ``[N, 3E]`` per-Gaussian features are rasterized
like any field's features, and each view's level maps are scored by the same query engine and
evaluation code. Training writes ``RUN/lift.pt`` from its own cached weights
(``TrainConfig.lift``); :func:`n2f2.query.lifted.build_lift` computes the weights otherwise.

Levels of a bank (:func:`bank_level_rule`): the ground-truth segmenter's layers are its levels
(part, object, group); LangSplat's files have levels (default, s, m, l), of which s, m, l are
LangSplat's three; any other bank (SAM, classical) is split by the terciles of the quantized
scale, as the ``levels`` field is supervised (:func:`n2f2.segments.bins.three_level_groups`),
a pixel taking the smallest covering segment of each tercile. Segments the bank marks invalid
(no lifted scale) carry no supervision in training and are left out here too.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import TYPE_CHECKING, Any, Optional, Sequence

import numpy as np
import torch
from torch import Tensor

from ..errors import InputError
from .variants import LEVEL_NAMES, NUM_LEVELS

if TYPE_CHECKING:
    from ..segments.bank import ImageSegments, SegmentBank

LIFT_LEVELS = LEVEL_NAMES  # level order of the lifted features: the levels field's


# ------------------------------------------------------------------------------ bank levels
def bank_level_rule(bank: Any) -> tuple[str, Optional[tuple[int, ...]]]:
    """How a bank's segments map to the 3 levels: ``("layers", (i_part, i_object, i_group))``
    when its layers are levels, else ``("terciles", None)`` (see the module docstring)."""
    spec = dict(getattr(bank, "segmenter_spec", {}) or {})
    levels = [str(v) for v in spec.get("levels") or []]
    if spec.get("name") == "langsplat" and levels[-3:] == ["s", "m", "l"]:
        return "layers", (len(levels) - 3, len(levels) - 2, len(levels) - 1)
    if len(levels) == NUM_LEVELS:
        return "layers", (0, 1, 2)
    return "terciles", None


def level_segments(
    record: ImageSegments,  # layers [L, H, W], valid, areas, quantized
    rule: tuple[str, Optional[tuple[int, ...]]],  # from bank_level_rule
) -> np.ndarray:  # [3, H, W] int64 segment id per level, -1 = none
    """The bank segment covering each pixel at each level (part, object, group)."""
    layers = np.asarray(record.layers)
    L, H, W = layers.shape
    S = int(np.asarray(record.areas).shape[0])
    valid = np.asarray(record.valid, dtype=bool) & (np.asarray(record.areas) > 0)
    out = np.full((NUM_LEVELS, H, W), -1, np.int64)
    kind, idx = rule
    if kind == "layers":
        for level, layer in enumerate(idx or ()):
            if 0 <= layer < L:
                ids = layers[layer].astype(np.int64)
                ok = ids >= 0
                ok[ok] = valid[ids[ok]]
                out[level] = np.where(ok, ids, -1)
        return out
    from ..segments.bins import three_level_groups

    group = np.asarray(three_level_groups(np.asarray(record.quantized, dtype=np.float64)), np.int64)  # [S]
    group = np.where(valid, group, -1)
    area = np.asarray(record.areas, dtype=np.float64)
    best = np.full((NUM_LEVELS, H, W), np.inf)
    for layer in layers:  # the smallest covering segment of each tercile
        ids = layer.astype(np.int64)
        for level in range(NUM_LEVELS):
            ok = ids >= 0
            ok[ok] = group[ids[ok]] == level
            a = np.where(ok, area[np.clip(ids, 0, max(S - 1, 0))] if S else np.inf, np.inf)
            take = a < best[level]
            out[level][take] = ids[take]
            best[level][take] = a[take]
    return out


# ------------------------------------------------------------------------------ the lift
@dataclass
class Lift:
    """Per-Gaussian features at the 3 levels (see the module docstring)."""

    features: Tensor  # [N, 3, E] float32, unit length per (Gaussian, level), 0 = never covered
    weights: Tensor  # [N, 3] float32 summed blending weight over the covered pixels
    views: list[int]  # scene views lifted from
    rule: str  # "layers" | "terciles" (bank_level_rule)
    seconds: dict[str, float] = dc_field(default_factory=dict)  # "blend" (0 when given), "lift", "total"

    @property
    def flat(self) -> Tensor:  # [N, 3E] the level blocks side by side (part first)
        return self.features.reshape(self.features.shape[0], -1)

    def coverage(self) -> list[float]:
        """Fraction of the Gaussians with a feature at each level."""
        return [float(v) for v in (self.weights > 0).float().mean(dim=0)]


LIFT_FORMAT = "n2f2-lift"
LIFT_VERSION = 1


def save_lift(path: Any, lift: Lift, meta: Optional[dict] = None) -> None:
    """Write ``lift`` atomically (features as float16, the bank's embedding precision)."""
    from ..io import save_torch
    from ..validate import check_finite

    blob = {
        "format": LIFT_FORMAT,
        "version": LIFT_VERSION,
        "features": lift.features.half(),
        "weights": lift.weights.float(),
        "views": list(lift.views),
        "rule": lift.rule,
        "seconds": dict(lift.seconds),
        "num_gaussians": int(lift.features.shape[0]),
        "meta": dict(meta or {}),
    }
    check_finite(path, {"features": blob["features"], "weights": blob["weights"]})
    save_torch(path, blob)


def load_lift(path: Any, num_gaussians: Optional[int] = None) -> Lift:
    """Read a file written by :func:`save_lift`; ``num_gaussians`` must match when given."""
    from pathlib import Path

    from ..io import load_torch

    path = Path(path)
    blob = load_torch(path, "lifted features")
    if not isinstance(blob, dict) or blob.get("format") != LIFT_FORMAT:
        raise InputError(path, "not lifted features written by n2f2 (format n2f2-lift)")
    if int(blob.get("version", 0)) > LIFT_VERSION:
        raise InputError(path, f"lift format version {blob['version']} is newer than this n2f2 ({LIFT_VERSION})")
    feats = blob["features"].float()
    if num_gaussians is not None and int(feats.shape[0]) != int(num_gaussians):
        raise InputError(path, f"the lift holds {feats.shape[0]} Gaussians, the run has {num_gaussians}")
    return Lift(
        feats,
        blob["weights"].float(),
        [int(v) for v in blob["views"]],
        str(blob["rule"]),
        {k: float(v) for k, v in blob.get("seconds", {}).items()},
    )


def lift_features(
    cache: Any,  # train.blend.BlendCache (a later stage, not imported): `views`' blending weights, in order
    views: Sequence[int],  # scene views the cache holds (the training views)
    bank: SegmentBank,
    num_gaussians: int,
) -> Lift:
    """Lift the bank's per-view features onto the Gaussians in one pass over the cached views
    (the trainer's cache, or :func:`n2f2.query.lifted.build_lift` which computes one)."""
    t0 = time.perf_counter()
    views = [int(v) for v in views]
    if not views:
        raise InputError(getattr(bank, "root", None), "no views to lift features from")
    sizes = bank.sizes
    if len(cache.sizes) != len(views) or any(tuple(cache.sizes[k]) != tuple(sizes[v]) for k, v in enumerate(views)):
        raise ValueError(
            f"the blend cache holds {len(cache.sizes)} views of sizes {sorted(set(cache.sizes))}; "
            f"the lift needs the {len(views)} given views at the bank's size"
        )
    N = int(num_gaussians)
    rule = bank_level_rule(bank)
    num, den = _weighted_sums(cache, views, bank, rule, N)
    feats = torch.nn.functional.normalize(num, dim=-1).reshape(N, NUM_LEVELS, -1).contiguous()
    return Lift(feats, den.float().reshape(N, NUM_LEVELS), views, rule[0], {"lift": time.perf_counter() - t0})


_DENSE_BINS = 1 << 24  # (Gaussian, level, segment) bins of one view summed in a dense buffer up to this many


def _triple_sums_kernel(crow, gid, weight, seg, S, acc, touched):  # pragma: no cover - compiled by numba
    """Sum the blending weights of each (Gaussian, level, segment) triple of one view into the
    dense ``acc [3 N S]``, listing each triple's bin in ``touched`` the first time it is hit
    (weights are positive); returns how many were listed."""
    n = 0
    P = seg.shape[1]
    for p in range(P):
        for level in range(3):
            s = seg[level, p]
            if s < 0:
                continue
            for e in range(crow[p], crow[p + 1]):
                k = (gid[e] * 3 + level) * S + s
                if acc[k] == 0.0:
                    touched[n] = k
                    n += 1
                acc[k] += weight[e]
    return n


_KERNEL: Optional[Any] = None  # the compiled kernel, False without numba


def _compiled_kernel() -> Optional[Any]:
    """:func:`_triple_sums_kernel` compiled by numba on first use (cached on disk), or None."""
    global _KERNEL
    if _KERNEL is None:
        try:
            import numba
        except ImportError:  # pragma: no cover - numba is a declared dependency
            _KERNEL = False
        else:
            _KERNEL = numba.njit(
                "int64(int64[:], int32[:], float32[:], int64[:, :], int64, float64[:], int64[:])",
                cache=True,
                nogil=True,
            )(_triple_sums_kernel)
    return _KERNEL or None


def _view_triples(
    crow: Tensor,  # [P + 1] long entry offsets of the view's pixels (from 0)
    gid: Tensor,  # [nnz] int32 Gaussian of each entry
    weight: Tensor,  # [nnz] float32 blending weight
    seg: Tensor,  # [3, P] long segment per level, -1 = none
    S: int,
    N: int,
    buffer: dict,
) -> tuple[Tensor, Tensor]:  # keys [T] long, sums [T] float64
    """The summed weight of every (Gaussian, level, segment) triple the view's entries hit, keyed
    ``(g * 3 + level) * S + segment``."""
    bins = N * NUM_LEVELS * S
    kernel = _compiled_kernel() if bins <= _DENSE_BINS else None
    if kernel is not None:
        acc = buffer.get("acc")
        if acc is None or acc.size < bins:
            acc = buffer["acc"] = np.zeros(max(bins, _DENSE_BINS // 16))
        touched = np.empty(min(bins, NUM_LEVELS * int(gid.shape[0])), np.int64)
        n = kernel(crow.numpy(), gid.numpy(), weight.numpy(), seg.numpy(), S, acc, touched)
        keys = touched[:n]
        sums = acc[keys]
        acc[keys] = 0.0  # the buffer is all zeros again for the next view
        return torch.from_numpy(keys.copy()), torch.from_numpy(sums)
    counts = crow[1:] - crow[:-1]
    g3 = gid.long() * NUM_LEVELS
    w = weight.double()
    keys, ws = [], []
    for level in range(NUM_LEVELS):
        s = torch.repeat_interleave(seg[level], counts)  # [nnz]
        keep = torch.nonzero(s >= 0).squeeze(1)
        keys.append((g3.index_select(0, keep) + level) * S + s.index_select(0, keep))
        ws.append(w.index_select(0, keep))
    uniq, inv = torch.unique(torch.cat(keys), return_inverse=True)
    return uniq, torch.zeros(uniq.shape[0], dtype=torch.float64).index_add_(0, inv, torch.cat(ws))


def _weighted_sums(
    cache: Any, views: Sequence[int], bank: Any, rule: tuple, N: int
) -> tuple[Tensor, Tensor]:  # num [3N, E] float32, den [3N] float64
    """``sum_p w f`` and ``sum_p w`` per (Gaussian, level) over the cached views.

    Per view, the weights of each (Gaussian, level, segment) triple are summed first, so the
    embeddings are multiplied once per triple, not once per blending entry: one sparse
    ``[3N, S_total] x [S_total, E]`` product in the end."""
    from ..sparse import csr_matrix

    crow = cache.crow.cpu()
    gid_all = cache.gid.cpu().to(torch.int32)
    w_all = cache.weight.cpu().float()
    rows, cols, vals, embs = [], [], [], []
    first = 0  # global id of the view's segment 0
    buffer: dict = {}
    for k, v in enumerate(views):
        rec = bank.record(v)
        emb = torch.from_numpy(np.asarray(rec.embeddings, dtype=np.float32))  # [S, E]
        S = int(emb.shape[0])
        seg = torch.from_numpy(level_segments(rec, rule).reshape(NUM_LEVELS, -1))  # [3, P]
        P = seg.shape[1]
        r0 = cache.offsets[k]
        e0, e1 = int(crow[r0]), int(crow[r0 + P])
        if S and e1 > e0:
            key, total = _view_triples(
                (crow[r0 : r0 + P + 1] - e0).contiguous(),
                gid_all[e0:e1].contiguous(),
                w_all[e0:e1].contiguous(),
                seg.contiguous(),
                S,
                N,
                buffer,
            )
            rows.append(torch.div(key, S, rounding_mode="floor"))
            cols.append(key % S + first)
            vals.append(total)
        embs.append(emb)
        first += S
    E = int(bank.embed_dim)
    if not rows:
        return torch.zeros(N * NUM_LEVELS, E), torch.zeros(N * NUM_LEVELS, dtype=torch.float64)
    row, col, val = torch.cat(rows), torch.cat(cols), torch.cat(vals)
    order = torch.argsort(row)
    row, col, val = row.index_select(0, order), col.index_select(0, order), val.index_select(0, order)
    crow_l = torch.zeros(N * NUM_LEVELS + 1, dtype=torch.long)
    crow_l[1:] = torch.cumsum(torch.bincount(row, minlength=N * NUM_LEVELS), 0)
    A = csr_matrix(crow_l, col, val.float(), (N * NUM_LEVELS, first))  # [3N, S_total]
    num = A @ torch.cat(embs)  # [3N, E]
    den = torch.zeros(N * NUM_LEVELS, dtype=torch.float64).index_add_(0, row, val)
    return num, den


# ------------------------------------------------------------------------------ level blocks
class LevelBlocks:
    """The stand-in "field" of features stored as 3 level blocks ``[.., 3E]`` (part first): the
    query engine's ``W [E, 3E]`` (the sum of the levels) and the level read-out."""

    def __init__(self, embed_dim: int, device: Any = "cpu") -> None:
        self.embed_dim = int(embed_dim)
        eye = torch.eye(self.embed_dim, device=device)
        self.W = torch.cat([eye] * NUM_LEVELS, dim=1)  # [E, 3E]

    def level_features(self, theta: Tensor) -> Tensor:  # [..., 3E] -> [..., 3, E]
        return theta.reshape(*theta.shape[:-1], NUM_LEVELS, self.embed_dim)

    def selectors(self) -> Tensor:  # [3, E, 3E]: level l = selectors[l] @ theta
        E = self.embed_dim
        out = torch.zeros(NUM_LEVELS, E, NUM_LEVELS * E, device=self.W.device)
        for level in range(NUM_LEVELS):
            out[level, :, level * E : (level + 1) * E] = torch.eye(E, device=self.W.device)
        return out
