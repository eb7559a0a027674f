"""The nested feature field: TriPlane+MLP (or PE+MLP) backbone ``Theta: R^3 -> R^D`` queried at
the Gaussian centres, and the zero-initialised scale-aware projection ``W [E, D]``
(paper Sec. 3.1-3.2)."""

from .._lazy import lazy_exports

__getattr__, __all__ = lazy_exports(
    __name__,
    {
        "FieldConfig": "model",
        "NestedField": "model",
        "bbox_from_points": "model",
        "build_field": "model",
        "check_embed_dim": "model",
        "gaussian_features": "model",
        "level_blocks": "model",
        "load_field": "model",
        "prefix_mask": "model",
        "save_field": "model",
        "PositionalEncoding": "triplane",
        "TriPlane": "triplane",
    },
)
