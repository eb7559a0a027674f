"""Feature-field training with hierarchical supervision (paper Sec. 3.2): pixel and segment
sampling, deferred rendering, the L2 + cosine loss, checkpoints, and the per-level cosine
evaluation on held-out views.

Names are imported lazily so ``import n2f2.train`` (the CLI does it) stays cheap."""

from __future__ import annotations

from .._lazy import lazy_exports

_EXPORTS = {
    "TrainConfig": "trainer",
    "train_field": "trainer",
    "field_preset": "trainer",
    "hierarchical_loss": "trainer",
    "saved_configs": "trainer",
    "ViewSegments": "sampling",
    "SegmentPool": "sampling",
    "sample_segments": "sampling",
    "segment_weights": "sampling",
    "covering_probabilities": "sampling",
    "evaluate_cosine_by_level": "evaluate",
    "cosine_table": "evaluate",
}

__getattr__, __all__ = lazy_exports(__name__, _EXPORTS)
