"""The segment bank stage: multi-granularity segments, their language embeddings, their 3D
scales and the quantile scale bins (paper Sec. 3.2 "Extracting Training Data").

* :mod:`.segmenters`: ``sam`` / ``classical`` / ``ground-truth`` -> :class:`SegmentSet`
* :mod:`.encoders`: ``clip`` / ``captions`` (offline stand-in for CLIP) -> embeddings
* :mod:`.langsplat`: LangSplat ``language_features`` import
* :mod:`.lifting`: depth -> 3D points -> scale (largest covariance eigenvalue, or robust extent)
* :mod:`.bins`: quantile transform, ``M(s)`` with step size k
* :mod:`.bank`: the on-disk bank, :class:`SegmentBank` reader, :func:`build_bank`

Names are imported lazily, so ``import n2f2.segments`` (the CLI does it) stays cheap.
"""

from __future__ import annotations

from .._lazy import lazy_exports

_EXPORTS = {
    "SegmentBank": "bank",
    "ImageSegments": "bank",
    "build_bank": "bank",
    "SegmentAndEncode": "bank",
    "QuantileScaleBins": "bins",
    "scale_to_dims": "bins",
    "three_level_groups": "bins",
    "get_encoder": "encoders",
    "ClipEncoder": "encoders",
    "CaptionEncoder": "encoders",
    "get_segmenter": "segmenters",
    "SegmentSet": "segmenters",
    "SamSegmenter": "segmenters",
    "ClassicalSegmenter": "segmenters",
    "GroundTruthSegmenter": "segmenters",
    "mask_nms": "segmenters",
    "LangSplatSource": "langsplat",
    "read_langsplat": "langsplat",
    "segment_scales": "lifting",
    "LiftSettings": "lifting",
}

__getattr__, __all__ = lazy_exports(__name__, _EXPORTS)
