"""The nested feature field: TriPlane+MLP (or PE+MLP) backbone ``Theta: R^3 -> R^D`` queried at
the Gaussian centres, and the zero-initialised scale-aware projection ``W [E, D]``
(paper Sec. 3.1-3.2)."""

from .model import (FieldConfig, NestedField, bbox_from_points, build_field, check_embed_dim,
                    gaussian_features, level_blocks, load_field, prefix_mask, save_field)
from .triplane import PositionalEncoding, TriPlane

__all__ = ["FieldConfig", "NestedField", "PositionalEncoding", "TriPlane", "bbox_from_points",
           "build_field", "check_embed_dim", "gaussian_features", "level_blocks", "load_field",
           "prefix_mask", "save_field"]
