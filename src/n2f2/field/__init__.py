"""The nested feature field: TriPlane+MLP (or PE+MLP) backbone ``Theta: R^3 -> R^D`` queried at
the Gaussian centres, and the zero-initialised scale-aware projection ``W [E, D]``
(paper Sec. 3.1-3.2), its variants (:mod:`.variants`: nested, flat, levels) as objects, and the
one relevancy score of its language features against text (:mod:`.relevancy`)."""

from typing import TYPE_CHECKING

from .._lazy import lazy_exports

if TYPE_CHECKING:  # the lazily exported names, for static analysis
    from .model import FieldConfig as FieldConfig
    from .model import NestedField as NestedField
    from .model import bbox_from_points as bbox_from_points
    from .model import build_field as build_field
    from .model import check_embed_dim as check_embed_dim
    from .model import gaussian_features as gaussian_features
    from .model import load_field as load_field
    from .model import prefix_mask as prefix_mask
    from .model import save_field as save_field
    from .relevancy import DEFAULT_NEGATIVES as DEFAULT_NEGATIVES
    from .relevancy import normalize_features as normalize_features
    from .relevancy import relevancy as relevancy
    from .relevancy import relevancy_from_scores as relevancy_from_scores
    from .triplane import PositionalEncoding as PositionalEncoding
    from .triplane import TriPlane as TriPlane
    from .variants import LEVEL_NAMES as LEVEL_NAMES
    from .variants import VARIANTS as VARIANTS
    from .variants import FieldVariant as FieldVariant
    from .variants import get_variant as get_variant
    from .variants import level_blocks as level_blocks

__getattr__, __all__ = lazy_exports(
    __name__,
    {
        "FieldConfig": "model",
        "NestedField": "model",
        "bbox_from_points": "model",
        "build_field": "model",
        "check_embed_dim": "model",
        "gaussian_features": "model",
        "load_field": "model",
        "prefix_mask": "model",
        "save_field": "model",
        "DEFAULT_NEGATIVES": "relevancy",
        "normalize_features": "relevancy",
        "relevancy": "relevancy",
        "relevancy_from_scores": "relevancy",
        "PositionalEncoding": "triplane",
        "TriPlane": "triplane",
        "FieldVariant": "variants",
        "LEVEL_NAMES": "variants",
        "VARIANTS": "variants",
        "get_variant": "variants",
        "level_blocks": "variants",
    },
)
