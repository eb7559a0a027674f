"""Feature-field training with hierarchical supervision (paper Sec. 3.2): pixel and segment
sampling, deferred rendering, the L2 + cosine loss, checkpoints, and the per-level cosine
evaluation on held-out views.

Names are imported lazily so ``import n2f2.train`` (the CLI does it) stays cheap."""

from __future__ import annotations

import importlib

_EXPORTS = {
    "TrainConfig": "trainer", "train_field": "trainer", "field_preset": "trainer",
    "hierarchical_loss": "trainer", "saved_configs": "trainer",
    "ViewSegments": "sampling", "sample_pixels": "sampling", "sample_segments": "sampling",
    "segment_weights": "sampling", "covering_probabilities": "sampling",
    "evaluate_cosine_by_level": "evaluate", "cosine_table": "evaluate",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
