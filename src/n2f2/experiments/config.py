"""The bench's settings (:class:`BenchConfig`) and the data every variant trains on
(:class:`BenchData`): what :mod:`.bench` runs with and :mod:`.training`, :mod:`.evaluate` and
:mod:`.timing` take, kept apart from the run so that those modules need not import it."""

from __future__ import annotations

import math
from dataclasses import dataclass
from dataclasses import field as dc_field
from pathlib import Path
from typing import Any, Optional

from ..pipeline.presets import get_preset
from ..pipeline.run import DemoScene
from ..segments.lifting import SCALE_MEASURES
from .variants import DEFAULT_VARIANTS, VARIANTS

# Composite temperatures of Eq. 6: 1 = the paper (the bench's main rows), inf = the plain mean of the scale features.
TEMPERATURES = (1.0, math.inf, 0.1, 0.01)
_CPU = get_preset("cpu")  # the defaults the bench shares with `n2f2 run`
_SCENE = DemoScene()  # the default demo scene


@dataclass
class BenchConfig:
    """Settings of :func:`.bench.run_bench`. Defaults: the full bench on the default demo scene, sized to
    finish in about 30 minutes on 2 CPU cores once the Gaussians exist (see :meth:`quick`)."""

    iterations: int = 1000  # training steps per variant (fewer than the cpu preset's, to keep ~30 min)
    dim: int = _CPU.field.dim  # D of every field (paper 512; k is scaled to keep the number of scales)
    pixels_per_step: int = _CPU.train.pixels_per_step
    # The cpu preset's departures from the paper (the paper: eigenvalue, 0); see
    # LiftSettings.scale_measure and TrainConfig.scale_jitter.
    scale_measure: str = _CPU.lift.scale_measure
    scale_jitter: float = _CPU.train.scale_jitter
    variants: tuple[str, ...] = DEFAULT_VARIANTS
    temperatures: tuple[float, ...] = TEMPERATURES  # composite T evaluated on the k=1 nested run
    timing_repeats: int = 5  # medians over this many repeats in the timing breakdown
    timing_threads: int = 1  # torch threads while timing (1: stable on a shared 2-core machine)
    # Scene generated when none is given (the default demo scene), and its Gaussian fit.
    scene_views: int = _SCENE.views
    scene_width: int = _SCENE.width
    scene_height: int = _SCENE.height
    fit_steps: Optional[int] = None  # None: the cpu preset's schedule sized to the scene
    seed: int = 0
    device: str = "cpu"
    progress: bool = True

    def __post_init__(self) -> None:
        unknown = [v for v in self.variants if v not in VARIANTS]
        if unknown:
            raise ValueError(f"unknown variant(s) {unknown}; choose from {list(VARIANTS)}")
        if self.iterations < 1:
            raise ValueError(f"iterations must be >= 1, got {self.iterations}")
        if self.dim < 3:
            raise ValueError(f"dim must be >= 3, got {self.dim}")
        if self.scale_measure not in SCALE_MEASURES:
            raise ValueError(f"scale_measure must be one of {SCALE_MEASURES}, got {self.scale_measure!r}")
        if not 0.0 <= self.scale_jitter < 1.0:
            raise ValueError(f"scale_jitter must be in [0, 1), got {self.scale_jitter}")
        if not self.temperatures or any(not t > 0 for t in self.temperatures):
            raise ValueError(f"temperatures must be positive, got {self.temperatures}")
        self.variants = tuple(dict.fromkeys(self.variants))
        self.temperatures = tuple(dict.fromkeys(float(t) for t in self.temperatures))

    @staticmethod
    def quick(**overrides: Any) -> "BenchConfig":
        """A few minutes: small generated scene, D = 32, short training, fewer timing repeats."""
        base: dict[str, Any] = dict(
            iterations=150,
            dim=32,
            pixels_per_step=2048,
            timing_repeats=2,
            scene_views=16,
            scene_width=96,
            scene_height=72,
            fit_steps=300,
        )
        base.update(overrides)
        return BenchConfig(**base)


@dataclass
class BenchData:
    """The scene, Gaussians and segment bank every variant trains on."""

    scene_dir: Path
    gaussians: Path
    bank_dir: Path
    label_dir: Path
    built: dict[str, bool] = dc_field(default_factory=dict)  # stage -> built now (False: reused)
    seconds: dict[str, float] = dc_field(default_factory=dict)
