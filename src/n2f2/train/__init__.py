"""Feature-field training with hierarchical supervision (paper Sec. 3.2): pixel and segment
sampling, deferred rendering, the L2 + cosine loss, checkpoints, and the per-level cosine
evaluation on held-out views.

Names are imported lazily so ``import n2f2.train`` (the CLI does it) stays cheap."""

from __future__ import annotations

from typing import TYPE_CHECKING

from .._lazy import lazy_exports

if TYPE_CHECKING:  # the lazily exported names, for static analysis
    from .checkpoint import saved_configs as saved_configs
    from .config import TrainConfig as TrainConfig
    from .config import field_preset as field_preset
    from .evaluate import cosine_table as cosine_table
    from .evaluate import evaluate_cosine_by_level as evaluate_cosine_by_level
    from .losses import hierarchical_loss as hierarchical_loss
    from .sampling import SegmentPool as SegmentPool
    from .sampling import ViewSegments as ViewSegments
    from .sampling import covering_probabilities as covering_probabilities
    from .sampling import sample_segments as sample_segments
    from .sampling import segment_weights as segment_weights
    from .trainer import train_field as train_field

_EXPORTS = {
    "TrainConfig": "config",
    "train_field": "trainer",
    "field_preset": "config",
    "hierarchical_loss": "losses",
    "saved_configs": "checkpoint",
    "ViewSegments": "sampling",
    "SegmentPool": "sampling",
    "sample_segments": "sampling",
    "segment_weights": "sampling",
    "covering_probabilities": "sampling",
    "evaluate_cosine_by_level": "evaluate",
    "cosine_table": "evaluate",
}

__getattr__, __all__ = lazy_exports(__name__, _EXPORTS)
