"""The training settings: :class:`TrainConfig` with its presets, the field presets, and the
names of the files a training run writes."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, ClassVar

import numpy as np

from ..config import ConfigDict, option
from ..field.model import FieldConfig
from ..validate import nonneg_float, nonneg_int, positive_int

FIELD_NAME = "field.pt"
CHECKPOINT_NAME = "checkpoint.pt"
REPORT_NAME = "train_report.json"
GAUSSIANS_NAME = "gaussians.ply"
LIFT_NAME = "lift.pt"
RESULT_NAMES = (FIELD_NAME, CHECKPOINT_NAME, REPORT_NAME, LIFT_NAME)  # what a finished or started run holds


@dataclass
class TrainConfig(ConfigDict):
    """Optimisation settings. Defaults are the paper's (30k iterations, GPU); :meth:`cpu` is the
    preset for the built-in demo scene on a 2-core CPU."""

    PRESETS: ClassVar[tuple[str, ...]] = ("cpu", "paper")  # see the static methods of those names

    # Fields declared with option() are flags of `n2f2 train`; their help lists each preset's value.
    iterations: int = option(30_000, help="optimisation steps of the field", type=positive_int)
    views_per_step: int = option(
        1, help="views rasterized per step without --blend-cache; pixels are sampled across them", type=positive_int
    )
    # Test time always renders at full resolution.
    render_downscale: int = option(
        1,
        help="render training views downscaled by this integer factor, segment layers resampled to match; "
        "1 = bank resolution",
        type=positive_int,
    )
    # The Gaussians are frozen, so rasterizing is a fixed linear map (train/blend.py). ~1.8x
    # faster on CPU (86 vs 157 ms per demo step); falls back to rasterizing when the cache would
    # exceed blend_cache_mb.
    blend_cache: bool = option(
        False,
        help="precompute each view's blending weights once instead of rasterizing every step (exact); "
        "every step then samples pixels across all training views",
    )
    blend_cache_mb: float = 1024.0
    # With the blend cache: after training, average the bank's features onto the Gaussians with
    # the cached weights (the training-free `lift` baseline, field/lift.py) into RUN/lift.pt.
    lift: bool = False
    pixels_per_step: int = option(
        4096, help="sampled pixels per step, each with one sampled segment (or all, --every-segment)", type=positive_int
    )
    lr_triplane: float = 0.0016  # x scene extent (paper)
    lr_mlp: float = 0.00125  # MLP and W (paper)
    cos_weight: float = option(0.001, help="lambda of the cosine loss", type=nonneg_float)
    # A segment's lifted scale varies from view to view, so its M(s) does too; jitter makes
    # phi(u, s) vary smoothly in s.
    scale_jitter: float = option(
        0.0,
        help="half-width of the uniform noise added to each sampled quantized scale before B(s), not in the "
        "paper; 0 = off, as the paper",
        type=nonneg_float,
    )
    # Not in the paper: the loss's expectation over the segment draw instead of one draw
    # (train/sampling.py). The field runs once per pixel either way; the loss runs per row.
    every_segment: bool = option(
        False,
        help="supervise each sampled pixel with every segment covering it, weighted by the probability "
        "that the paper's draw of one segment picks it (same expected loss, less variance); "
        "off: one segment drawn per pixel, as the paper",
    )
    # Not in the paper: pixels drawn with probability ∝ (area of their smallest covering segment)^-b
    # (train/sampling.py), so a thin part's few pixels are drawn often enough to train its feature.
    pixel_balance: float = option(
        0.0,
        help="draw pixels with probability proportional to area^-B, the area of the smallest segment covering "
        "each, not in the paper; 0 = uniform pixels, as the paper; 1 = every smallest segment equally often",
        type=nonneg_float,
        metavar="B",
    )
    deferred: bool = option(
        True,
        help="deferred rendering (paper, training only): rasterize the backbone's features, MLP per pixel; "
        "--no-deferred: rasterize D-dim features, MLP per Gaussian",
    )
    holdout: bool = True  # leave scene.json's test_views out of training
    checkpoint_every: int = option(
        500, help="write checkpoint.pt every N steps; 0: only at the end", type=nonneg_int, metavar="N"
    )
    log_every: int = 10  # loss-curve sampling and progress-bar refresh
    seed: int = 0
    device: str = "cpu"

    def __post_init__(self) -> None:
        if not 0.0 <= self.scale_jitter < 1.0:  # NaN fails too
            raise ValueError(f"scale_jitter must be in [0, 1), got {self.scale_jitter}")
        for name in ("views_per_step", "render_downscale", "pixels_per_step", "log_every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        for name in ("iterations", "checkpoint_every", "seed"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise ValueError(f"{name} must be an integer >= 0, got {value!r}")
        for name in ("lr_triplane", "lr_mlp", "cos_weight", "blend_cache_mb", "pixel_balance"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")

    @staticmethod
    def paper() -> "TrainConfig":
        return TrainConfig()

    @staticmethod
    def cpu() -> "TrainConfig":
        """The built-in demo scene (40 views of 160x120) on 2 cores: 3000 steps of 2048 pixels at
        D = 128 with the blend cache, and three departures from the paper:

        * ``scale_jitter = 0.03``: a segment's lifted scale varies from view to view, and the
          jitter keeps phi(u, s) smooth in s, which mattered most for object and group features
          (held-out cosines per level with and without it: ``docs/measurements.md``, "The cpu
          training preset");
        * ``every_segment``: each sampled pixel is supervised by every segment covering it,
          weighted by the paper's draw probability (its expected loss). With half the paper's
          4096 pixels per step it scores as 4096 pixels with one drawn segment each, two seeds on
          each of two layouts, at two thirds of the step (``docs/measurements.md``, "Every
          covering segment per pixel");
        * ``pixel_balance = 0.5``: pixels drawn with probability ∝ (area of their smallest
          covering segment)^-1/2, halfway in the exponent between the paper's uniform pixels and
          every smallest segment equally often. Thin parts (a teapot's handle and spout) rank far
          better, and the mean average precision rises on both generated layouts
          (``docs/measurements.md``, "Balanced pixel sampling").

        Use ``--iterations`` (and ``--dim``) when minutes matter less."""
        return TrainConfig(
            iterations=3000,
            pixels_per_step=2048,
            every_segment=True,
            checkpoint_every=500,
            blend_cache=True,
            scale_jitter=0.03,
            pixel_balance=0.5,
            lift=True,
        )


def field_preset(name: str, **overrides: Any) -> FieldConfig:
    """``FieldConfig.preset(name)`` ("cpu" or "paper") with ``overrides`` applied."""
    return replace(FieldConfig.preset(name), **overrides)
