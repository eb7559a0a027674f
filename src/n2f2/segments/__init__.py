"""The segment bank stage: multi-granularity segments, their language embeddings, their 3D
scales and the quantile scale bins (paper Sec. 3.2 "Extracting Training Data").

* :mod:`.segmenters`: ``sam`` (:mod:`.sam`) / ``classical`` / ``ground-truth`` -> :class:`SegmentSet`
* :mod:`.encoders`: ``clip`` / ``captions`` (offline stand-in for CLIP) -> embeddings
* :mod:`.langsplat`: LangSplat ``language_features`` import
* :mod:`.lifting`: depth -> 3D points -> scale (largest covariance eigenvalue, robust extent or visible area)
* :mod:`.bins`: quantile transform, ``M(s)`` with step size k
* :mod:`.bank`: the on-disk bank, :class:`SegmentBank` reader, :func:`build_bank`

Names are imported lazily, so ``import n2f2.segments`` (the CLI does it) stays cheap.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from .._lazy import lazy_exports

if TYPE_CHECKING:  # the lazily exported names, for static analysis
    from .bank import ImageSegments as ImageSegments
    from .bank import SegmentAndEncode as SegmentAndEncode
    from .bank import SegmentBank as SegmentBank
    from .bank import build_bank as build_bank
    from .bins import QuantileScaleBins as QuantileScaleBins
    from .bins import scale_to_dims as scale_to_dims
    from .bins import three_level_groups as three_level_groups
    from .encoders import CaptionEncoder as CaptionEncoder
    from .encoders import ClipEncoder as ClipEncoder
    from .encoders import get_encoder as get_encoder
    from .langsplat import LangSplatSource as LangSplatSource
    from .langsplat import read_langsplat as read_langsplat
    from .lifting import LiftSettings as LiftSettings
    from .lifting import segment_scales as segment_scales
    from .sam import SamSegmenter as SamSegmenter
    from .segmenters import ClassicalSegmenter as ClassicalSegmenter
    from .segmenters import GroundTruthSegmenter as GroundTruthSegmenter
    from .segmenters import SegmentSet as SegmentSet
    from .segmenters import get_segmenter as get_segmenter
    from .segmenters import mask_nms as mask_nms

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
    "SamSegmenter": "sam",
    "ClassicalSegmenter": "segmenters",
    "GroundTruthSegmenter": "segmenters",
    "mask_nms": "segmenters",
    "LangSplatSource": "langsplat",
    "read_langsplat": "langsplat",
    "segment_scales": "lifting",
    "LiftSettings": "lifting",
}

__getattr__, __all__ = lazy_exports(__name__, _EXPORTS)
