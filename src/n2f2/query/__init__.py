"""Open-vocabulary querying (paper Sec. 3.3): composite embedding, explicit / levels / oracle
scale modes, 2D relevancy, segmentation and localization, 3D selection and PLY export.

Importing this package is cheap and has no side effects (no model is loaded)."""

from .._lazy import lazy_exports

__getattr__, __all__ = lazy_exports(
    __name__,
    {
        "DEFAULT_CANONICAL": "composite",
        "canonical_scores": "composite",
        "composite_weights": "composite",
        "prefix_dot": "composite",
        "prefix_sq_norms": "composite",
        "prefix_weights": "composite",
        "premultiply": "composite",
        "to_blocks": "composite",
        "MODES": "modes",
        "QUERY_MODES": "modes",
        "QueryMode": "modes",
        "get_mode": "modes",
        "QueryConfig": "engine",
        "QueryEngine": "engine",
        "QueryResult": "engine",
        "ViewCache": "engine",
        "build_composite_cache": "caches",
        "build_linear_cache": "caches",
        "build_prefix_cache": "caches",
    },
)
