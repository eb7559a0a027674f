"""The named presets of the whole pipeline, each one complete set of settings for every stage
(after nerfstudio's ``method_configs.py``): the Gaussian fit (:class:`FitConfig`), segment
lifting (:class:`LiftSettings`, the scale measure), the field (:class:`FieldConfig`) and its
training (:class:`TrainConfig`).

* ``cpu``: small scenes (the built-in demo) on a few CPU cores: the fit schedule is sized to
  the scene (:meth:`FitConfig.sized_for`), segments are measured by their visible area, and
  training jitters the sampled scales, supervises every covering segment of a pixel and draws
  pixels balanced towards small segments (none of them in the paper; :meth:`TrainConfig.cpu`);
* ``paper``: the paper's settings (3DGS's 30k-step fit, eigenvalue scales, D = 512 with
  TriPlane 512^2 x 64, 30k training steps).

``n2f2 run`` / ``demo`` / ``run-many`` and ``n2f2 bench`` read their defaults from here; the
stage commands (``fit-gaussians``, ``segments``, ``train``) use each stage's own preset
constructors, which these presets are built from.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Optional

from ..errors import InputError
from ..field.model import FieldConfig
from ..gaussians.fit import FitConfig
from ..segments.lifting import LiftSettings
from ..train.trainer import TrainConfig


@dataclass(frozen=True)
class Preset:
    """Every stage's settings under one name."""

    name: str
    fit: FitConfig  # before sizing to a scene (see sized_fit)
    sized_fit: bool  # derive the fit's steps, Gaussian cap and schedule from the scene
    lift: LiftSettings
    field: FieldConfig
    train: TrainConfig

    def fit_config(
        self,
        scene,
        steps: Optional[int] = None,
        seed: int = 0,  # scene: n2f2.data.Scene
        device: str = "cpu",
    ) -> FitConfig:
        """The fit settings for ``scene``; ``steps`` overrides the step count (a sized schedule
        keeps its fractions of the run)."""
        config = replace(self.fit, seed=seed)
        if self.sized_fit:
            config = config.sized_for(scene, steps=steps)
        config = replace(config, device=device)
        return replace(config, steps=steps) if steps is not None else config


def cpu() -> Preset:
    return Preset(
        name="cpu",
        fit=FitConfig.cpu(),
        sized_fit=True,
        lift=LiftSettings(scale_measure="area"),
        field=FieldConfig.cpu(),
        train=TrainConfig.cpu(),
    )


def paper() -> Preset:
    return Preset(
        name="paper",
        fit=FitConfig.paper(),
        sized_fit=False,
        lift=LiftSettings(),
        field=FieldConfig.paper(),
        train=TrainConfig.paper(),
    )


PRESETS: dict[str, Callable[[], Preset]] = {"cpu": cpu, "paper": paper}
DEFAULT_PRESET = "cpu"


def get_preset(name: str) -> Preset:
    """A fresh copy of preset ``name`` (its configs may be changed with ``dataclasses.replace``)."""
    if name not in PRESETS:
        raise InputError(None, f"unknown preset {name!r}; choose from {', '.join(PRESETS)}")
    return PRESETS[name]()
