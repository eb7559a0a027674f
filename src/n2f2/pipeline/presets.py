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

``n2f2 run`` / ``demo`` / ``run-many`` and ``n2f2 bench`` read their defaults from here. The
names, the default (:func:`n2f2.config.default_preset`: ``paper`` on CUDA, else ``cpu``) and
each stage's part of a preset live with that stage's config (``FitConfig.cpu``,
``FitConfig.for_scene`` for the sizing rule, ``TrainConfig.paper`` ...), so that a stage's
runner builds its config without importing the pipeline; these presets are built from them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ..config import DEFAULT_PRESET, PRESET_NAMES, default_preset
from ..errors import InputError
from ..field.model import FieldConfig
from ..gaussians.fit import FitConfig
from ..segments.lifting import LiftSettings
from ..train.config import TrainConfig

__all__ = ["DEFAULT_PRESET", "PRESETS", "PRESET_NAMES", "Preset", "default_preset", "get_preset"]


@dataclass(frozen=True)
class Preset:
    """Every stage's settings under one name."""

    name: str
    fit: FitConfig  # before sizing to a scene (FitConfig.for_scene)
    lift: LiftSettings
    field: FieldConfig
    train: TrainConfig


def cpu() -> Preset:
    return Preset(
        name="cpu",
        fit=FitConfig.cpu(),
        lift=LiftSettings.cpu(),
        field=FieldConfig.cpu(),
        train=TrainConfig.cpu(),
    )


def paper() -> Preset:
    return Preset(
        name="paper",
        fit=FitConfig.paper(),
        lift=LiftSettings.paper(),
        field=FieldConfig.paper(),
        train=TrainConfig.paper(),
    )


PRESETS: dict[str, Callable[[], Preset]] = {"cpu": cpu, "paper": paper}
assert tuple(PRESETS) == PRESET_NAMES  # every stage's config has a constructor of each name


def get_preset(name: str) -> Preset:
    """A fresh copy of preset ``name`` (its configs may be changed with ``dataclasses.replace``)."""
    if name not in PRESETS:
        raise InputError(None, f"unknown preset {name!r}; choose from {', '.join(PRESETS)}")
    return PRESETS[name]()
