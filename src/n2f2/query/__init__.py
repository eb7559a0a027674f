"""Open-vocabulary querying (paper Sec. 3.3): composite embedding, explicit / levels / oracle
scale modes, 2D relevancy, segmentation and localization, 3D selection and PLY export.

Importing this package is cheap and has no side effects (no model is loaded)."""

from .composite import (DEFAULT_CANONICAL, canonical_scores, composite_weights, prefix_dot,
                        prefix_sq_norms, prefix_weights, premultiply, supervised_dims, to_blocks)
from .engine import (MODES, QueryConfig, QueryEngine, QueryResult, ViewCache, build_composite_cache,
                     build_linear_cache, build_prefix_cache, export_selection_ply)
from .relevancy import DEFAULT_NEGATIVES, normalize_features, relevancy, relevancy_from_scores

__all__ = ["DEFAULT_CANONICAL", "DEFAULT_NEGATIVES", "MODES", "QueryConfig", "QueryEngine", "QueryResult",
           "ViewCache", "build_composite_cache", "build_linear_cache", "build_prefix_cache",
           "canonical_scores", "composite_weights", "export_selection_ply", "normalize_features",
           "prefix_dot", "prefix_sq_norms", "prefix_weights", "premultiply", "relevancy",
           "relevancy_from_scores", "supervised_dims", "to_blocks"]
