"""Training-sample selection (paper Sec. 3.2, "Hierarchical Loss Supervision"):

* pixels ``u`` are sampled uniformly across the training images (among pixels that at least
  one valid segment covers: the others carry no supervision), or, with ``balance = b > 0`` (not
  in the paper), with probability proportional to ``a^-b`` for ``a`` the area of the smallest
  valid segment covering the pixel (:func:`pixel_probabilities`). ``b = 1`` gives every finest
  segment the same share of the samples whatever its size, ``b = 0`` is the paper's uniform draw;
  a thin part's few pixels are otherwise drawn so rarely that its fine-scale feature barely trains;
* for each pixel, one of the segments covering it is sampled with probability proportional to
  ``1 / log(area)`` (small segments are preferred, so fine parts are not drowned by the large
  segments that cover every pixel).

:meth:`SegmentPool.sample_every_segment` (not in the paper) keeps every covering segment of each
sampled pixel instead, weighted by the probability that draw would give it: the weighted loss is
the expectation of the one-segment loss over the draw, so a step has the same expected gradient
with less variance, for the price of the loss (not the field) on a few rows per pixel.

A bank record stores an image's segments as non-overlapping id layers ``[L, H, W]``; the
segments covering pixel p are ``layers[:, p]`` (those >= 0 and valid).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch
from torch import Tensor

# log(area) is clamped below at log(MIN_AREA) so a one-pixel segment does not get infinite weight.
MIN_AREA = 2.0


def segment_weights(
    areas: Tensor,  # [S] pixel areas
    valid: Optional[Tensor] = None,  # [S] bool, invalid segments get weight 0
) -> Tensor:  # [S] float64 unnormalised weights 1 / log(area)
    """The paper's per-segment sampling weight ``1 / log(area)``."""
    w = 1.0 / torch.log(areas.double().clamp(min=MIN_AREA))
    if valid is not None:
        w = torch.where(valid.bool(), w, torch.zeros_like(w))
    return w


def covering_probabilities(
    candidates: Tensor,  # [P, L] segment id per layer, -1 = none
    weights: Tensor,  # [S] from segment_weights
) -> Tensor:  # [P, L] row-normalised probabilities (0 rows stay 0)
    """Probability of choosing each covering segment of each pixel (layer order)."""
    w = torch.where(candidates >= 0, weights[candidates.clamp(min=0)], torch.zeros((), dtype=weights.dtype))
    total = w.sum(dim=1, keepdim=True)
    return w / total.clamp(min=torch.finfo(w.dtype).tiny)


@dataclass
class ViewSegments:
    """One training view's segments in the flat form sampling needs (built once)."""

    view: int  # scene view index
    layers: Tensor  # [L, H*W] long segment id, -1 = none (invalid segments already removed)
    weights: Tensor  # [S] float64, 1 / log(area), 0 for invalid segments
    covered: Tensor  # [K] long flat pixel indices with at least one valid segment
    quantized: Tensor  # [S] float32 quantized scale s in [0, 1)
    embeddings: Tensor  # [S, E] float32 teacher embeddings
    areas: Tensor  # [S] float64 pixel areas (the bank's)

    @staticmethod
    def from_record(view: int, record, size: Optional[tuple[int, int]] = None) -> "ViewSegments":
        """From a bank record (``layers [L, H, W]``, ``embeddings``, ``quantized``, ``areas``,
        ``valid``). ``size = (height, width)`` resamples the layers (nearest, at pixel centres)
        to the resolution the training renders at; segment areas stay the bank's."""
        layers = np.asarray(record.layers)
        if size is not None and tuple(size) != layers.shape[1:]:
            from ..segments.segmenters import resize_nearest

            layers = resize_nearest(layers, int(size[0]), int(size[1]))
        layers = torch.from_numpy(np.array(layers, dtype=np.int64))  # [L, H, W] (copy: records are mmapped)
        L = layers.shape[0]
        layers = layers.reshape(L, -1)
        S = int(np.asarray(record.areas).shape[0])
        valid = (
            torch.from_numpy(np.array(record.valid, dtype=bool))
            if record.valid is not None
            else torch.ones(S, dtype=torch.bool)
        )
        areas = torch.from_numpy(np.array(record.areas, dtype=np.float64))
        weights = segment_weights(areas, valid)
        # Drop ids of invalid segments so every remaining candidate has a positive weight.
        if S:
            keep = layers >= 0
            keep &= weights[layers.clamp(min=0)] > 0
            layers = torch.where(keep, layers, torch.full_like(layers, -1))
        covered = torch.nonzero((layers >= 0).any(dim=0)).squeeze(1) if L else torch.zeros(0, dtype=torch.long)
        return ViewSegments(
            view=view,
            layers=layers,
            weights=weights,
            covered=covered,
            quantized=torch.as_tensor(np.asarray(record.quantized, dtype=np.float32)),
            embeddings=torch.as_tensor(np.asarray(record.embeddings, dtype=np.float32)),
            areas=areas,
        )


def pixel_probabilities(
    candidates: Tensor,  # [K, L] segment ids covering each pixel, -1 = none (each row has one)
    areas: Tensor,  # [S] pixel areas of the segments
    balance: float,  # b >= 0
) -> Tensor:  # [K] float64, sums to 1
    """Probability of drawing each pixel: ``a_min^-b / sum``, ``a_min`` the smallest area among the
    segments covering the pixel (clamped below at 1)."""
    a = areas.double().clamp(min=1.0)[candidates.clamp(min=0)]  # [K, L]
    finest = torch.where(candidates >= 0, a, torch.full_like(a, float("inf"))).amin(dim=1)  # [K]
    w = finest.pow(-float(balance))
    return w / w.sum()


@dataclass
class PixelBatch:
    """Sampled supervision: P pixels (``pixel[i]`` of rendered view ``slot[i]``, an index into
    the views rendered this step) and R (pixel, segment) rows. Row r supervises pixel ``row[r]``
    with a segment's quantized scale and its id in the pool (its teacher embedding is the pool's
    ``embeddings[pooled[r]]``, gathered once per distinct segment by the loss), and counts
    ``weight[r]`` times in the loss. One sampled segment per pixel: R = P, ``row = arange(P)``,
    weights 1; every covering segment: the weights of a pixel's rows sum to 1."""

    slot: Tensor  # [P] long, index into the step's views
    pixel: Tensor  # [P] long, flat pixel index (row * W + col)
    row: Tensor  # [R] long, the row's pixel: an index into slot / pixel
    segment: Tensor  # [R] long, local segment id within that view
    scale: Tensor  # [R] float32 quantized scale
    pooled: Tensor  # [R] long, the segment's id in the SegmentPool it came from
    weight: Tensor  # [R] float32, the row's share of its pixel's loss


def sample_segments(
    candidates: Tensor,  # [P, L]
    weights: Tensor,  # [S]
    generator: torch.Generator,
) -> Tensor:  # [P] chosen segment id
    """One covering segment per pixel, with probability ∝ 1 / log(area) (every row must have
    at least one candidate)."""
    probs = covering_probabilities(candidates, weights)  # [P, L]
    choice = torch.multinomial(probs.float(), 1, generator=generator).squeeze(1)  # [P]
    return candidates.gather(1, choice[:, None]).squeeze(1)


@dataclass
class SegmentPool:
    """The covered pixels of several views and their candidate segments, concatenated so that a
    step samples all its pixels and segments with a few tensor ops (no loop over views)."""

    slot: Tensor  # [K] long, index into the pooled views of each covered pixel
    pixel: Tensor  # [K] long, flat pixel index in that view
    candidates: Tensor  # [K, L] long, pooled segment ids covering the pixel, -1 = none
    weights: Tensor  # [S] float64, 1 / log(area) of each pooled segment
    local: Tensor  # [S] long, the segment's id within its view
    quantized: Tensor  # [S] float32
    embeddings: Tensor  # [S, E] float32
    cdf: Optional[Tensor] = None  # [K] float64 cumulative pixel probabilities; None: uniform pixels

    @staticmethod
    def from_views(views: list[ViewSegments], balance: float = 0.0) -> "SegmentPool":
        """Pool ``views``; ``balance = b > 0`` draws pixels by :func:`pixel_probabilities`, 0
        uniformly (the paper)."""
        if not views:
            raise ValueError("no views to sample from")
        if not (np.isfinite(balance) and balance >= 0):
            raise ValueError(f"pixel balance must be a finite number >= 0, got {balance!r}")
        L = max(v.layers.shape[0] for v in views)
        slot, pixel, cand, weights, local, quant, emb, areas = [], [], [], [], [], [], [], []
        first = 0  # pooled id of the view's segment 0
        for k, v in enumerate(views):
            c = v.layers[:, v.covered].t()  # [K_v, L_v]
            c = torch.where(c >= 0, c + first, c)
            cand.append(torch.nn.functional.pad(c, (0, L - c.shape[1]), value=-1))
            slot.append(torch.full_like(v.covered, k))
            pixel.append(v.covered)
            S = v.weights.shape[0]
            weights.append(v.weights)
            local.append(torch.arange(S))
            quant.append(v.quantized)
            emb.append(v.embeddings)
            areas.append(v.areas)
            first += S
        candidates = torch.cat(cand)
        cdf = None
        if balance > 0 and candidates.shape[0]:
            cdf = pixel_probabilities(candidates, torch.cat(areas), balance).cumsum_(0)
        return SegmentPool(
            torch.cat(slot),
            torch.cat(pixel),
            candidates,
            torch.cat(weights),
            torch.cat(local),
            torch.cat(quant),
            torch.cat(emb),
            cdf,
        )

    def _pick(self, num_pixels: int, generator: torch.Generator) -> Tensor:  # [P] rows of the pool
        if self.pixel.numel() == 0:
            raise ValueError("no pixel of the selected views is covered by a valid segment")
        if self.cdf is None:
            return torch.randint(self.pixel.numel(), (num_pixels,), generator=generator)
        u = torch.rand(num_pixels, generator=generator, dtype=torch.float64) * self.cdf[-1]
        return torch.searchsorted(self.cdf, u, right=True).clamp_(max=self.pixel.numel() - 1)

    def sample(self, num_pixels: int, generator: torch.Generator) -> PixelBatch:
        """``num_pixels`` covered pixels, uniform or balanced (with replacement), each with one
        covering segment chosen ∝ 1 / log(area)."""
        pick = self._pick(num_pixels, generator)
        seg = sample_segments(self.candidates[pick], self.weights, generator)  # [P] pooled id
        ones = torch.ones(num_pixels, dtype=torch.float32)
        return PixelBatch(
            self.slot[pick], self.pixel[pick], torch.arange(num_pixels), self.local[seg], self.quantized[seg], seg, ones
        )

    def sample_every_segment(self, num_pixels: int, generator: torch.Generator) -> PixelBatch:
        """The pixels :meth:`sample` would draw (the same random stream for them), each with every
        covering segment as a row weighted by the probability that :meth:`sample` picks it."""
        pick = self._pick(num_pixels, generator)
        candidates = self.candidates[pick]  # [P, L]
        probs = covering_probabilities(candidates, self.weights)  # [P, L]
        row, layer = torch.nonzero(candidates >= 0, as_tuple=True)  # pixel-major
        seg = candidates[row, layer]  # [R] pooled id
        return PixelBatch(
            self.slot[pick],
            self.pixel[pick],
            row,
            self.local[seg],
            self.quantized[seg],
            seg,
            probs[row, layer].float(),
        )
