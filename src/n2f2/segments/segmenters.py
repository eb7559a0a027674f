"""Segmenters: an image in, class-agnostic multi-granularity segments out.

Every segmenter is a callable ``segmenter(image, view=None) -> SegmentSet`` with a ``name`` and
a ``settings`` dict (stored in ``bank.json``). A :class:`SegmentSet` keeps the segments of one
image as stacked *non-overlapping* id layers ``[L, H, W]`` (each segment lives in exactly one
layer, ids are local segment indices, -1 = none), which is also how the segment bank stores
them: compact, and the overlap SAM produces between a part and its object is kept because the
two go to different layers.

* ``sam``: SAM automatic mask generation as used by the paper and LangSplat, in :mod:`.sam`;
  the vectorised version of LangSplat's mask NMS it uses is in :mod:`.masks` (:func:`mask_nms`;
  theirs is a Python double loop over mask pairs).
* ``sam2``: the same automatic masks from SAM 2.1 (Hiera-tiny by default), in :mod:`.sam2`.
* ``classical``: multi-scale Felzenszwalb (scikit-image), for real photos without SAM weights.
* ``ground-truth``: the demo scene's part / object / group regions, with their captions.

:data:`SEGMENTERS` registers them by name (:class:`SegmenterKind`); :func:`get_segmenter` builds
one. Model-backed segmenters are imported only when built, so importing this module stays cheap.
"""

from __future__ import annotations

import importlib
from dataclasses import asdict, dataclass
from typing import Any, Callable, Optional

import numpy as np
import torch

from ..errors import InputError
from .masks import (  # the mask names are re-exported: the bank, tests and benchmarks import them from here
    SegmentSet,
    check_image,
    greedy_mask_nms,  # noqa: F401
    layers_to_masks,  # noqa: F401
    mask_nms,  # noqa: F401
    pack_layers,  # noqa: F401
    relabel_label_maps,
    remove_small_regions,  # noqa: F401
    resize_nearest,
    segment_areas,  # noqa: F401
    segment_layers,  # noqa: F401
)


# ----------------------------------------------------------------------------- classical
@dataclass
class ClassicalSettings:
    """Multi-scale Felzenszwalb graph segmentation: one partition per scale, fine to coarse."""

    scales: tuple[float, ...] = (100.0, 400.0, 1600.0)  # Felzenszwalb's k: larger = coarser
    sigma: float = 0.8  # Gaussian pre-smoothing (scikit-image default)
    min_area: int = 100  # regions below this many pixels are merged (min_size) and dropped


class ClassicalSegmenter:
    """Segments from Felzenszwalb's algorithm at several scales; each scale is one layer."""

    name = "classical"

    def __init__(self, settings: Optional[ClassicalSettings] = None) -> None:
        self.settings = settings or ClassicalSettings()

    @property
    def spec(self) -> dict:
        d = asdict(self.settings)
        d["scales"] = list(d["scales"])
        return {"name": self.name, **d}

    def __call__(self, image: np.ndarray, view: Optional[int] = None) -> SegmentSet:
        from skimage.segmentation import felzenszwalb

        image = check_image(image)
        st = self.settings
        labels = np.stack([felzenszwalb(image, scale=s, sigma=st.sigma, min_size=st.min_area) for s in st.scales])
        layers, _ = relabel_label_maps(labels, min_area=st.min_area)
        S = int(layers.max()) + 1 if layers.size else 0
        return SegmentSet(layers, np.ones(S, np.float32))


# ----------------------------------------------------------------------------- ground truth
class GroundTruthSegmenter:
    """The demo scene's ground-truth regions: layer 0 = parts, 1 = objects, 2 = groups, each
    segment carrying its caption (``regions.json``) and region id."""

    name = "ground-truth"

    def __init__(self, scene) -> None:
        if scene.ground_truth is None:
            raise InputError(
                scene.root,
                "--segmenter ground-truth needs a scene with ground-truth "
                "regions (regions/ and regions.json, as the built-in demo scene has)",
            )
        self.scene = scene
        gt = scene.ground_truth
        regions = gt.regions
        self.levels = list(regions.get("levels", ["part", "object", "group"]))
        self.captions = {int(r["id"]): str(r.get("caption") or r.get("name") or "") for r in regions["regions"]}

    @property
    def spec(self) -> dict:
        return {"name": self.name, "levels": self.levels}

    def __call__(self, image: np.ndarray, view: Optional[int] = None) -> SegmentSet:
        if view is None:
            raise ValueError("the ground-truth segmenter needs the view index")
        gt = self.scene.ground_truth
        path = gt.root / "regions" / f"{gt.image_names[view]}.npy"
        image = check_image(image)
        try:
            regions = np.asarray(gt.region_ids(view))
        except (OSError, ValueError) as e:
            raise InputError(path, f"cannot read ground-truth regions ({e})") from None
        if regions.ndim != 3:
            raise InputError(path, f"expected region ids [levels, H, W], got shape {regions.shape}")
        H, W = image.shape[:2]
        if regions.shape[1:] != (H, W):
            # Ground truth is stored at full resolution; the scene may be downscaled. Only an
            # aspect-preserving resize is legitimate.
            rh, rw = regions.shape[1:]
            if abs(rh / rw - H / W) > 0.02:
                raise InputError(path, f"region map size {rw}x{rh} does not match the image size {W}x{H}")
            regions = resize_nearest(regions, H, W)
        layers, source_ids = relabel_label_maps(regions)
        missing = [int(r) for r in source_ids if int(r) not in self.captions]
        if missing:
            raise InputError(gt.root / "regions.json", f"region ids {missing[:5]} used in {path.name} have no entry")
        captions = [self.captions[int(r)] for r in source_ids]
        return SegmentSet(layers, np.ones(len(source_ids), np.float32), captions=captions, source_ids=source_ids)


# ----------------------------------------------------------------------------- registry
@dataclass(frozen=True)
class SegmenterKind:
    """A segmenter that :func:`get_segmenter` can build by name.

    ``build(scene, model_id, device, settings)`` makes it; ``settings`` arrives as an instance of
    :meth:`settings_class` (None when the kind takes no settings) and ``model_id`` already
    defaults to ``default_model_id``. Builders import their module themselves, so registering a
    model-backed segmenter costs no import."""

    name: str
    build: Callable[..., Any]
    settings: str = ""  # "module:Class" in n2f2.segments, the dataclass of the keyword settings; "" = none
    default_model_id: Optional[str] = None  # Hugging Face id used when no model is given; None = no model
    needs_scene: bool = False  # builds from the scene (ground truth), not from images alone
    description: str = ""  # one line for a command-line help text
    # For a model-backed kind: what its loader calls the model, and what it offers instead
    # (as sam.py and sam2.py say when the model is missing).
    model_name: str = ""
    alternative: str = ""

    def settings_class(self) -> Optional[type]:
        """The settings dataclass (imports its module), or None."""
        if not self.settings:
            return None
        module, attr = self.settings.split(":")
        return getattr(importlib.import_module(f"{__package__}.{module}"), attr)

    def create(self, scene=None, model_id: Optional[str] = None, device: str | torch.device = "cpu", **settings):
        """Build the segmenter: check the scene is there if needed, make the settings (a
        TypeError names an unknown one), then load the model if any."""
        if self.needs_scene and scene is None:
            raise ValueError(f"the {self.name} segmenter needs the scene")
        cls = self.settings_class()
        made = None if cls is None else cls(**settings)
        return self.build(scene=scene, model_id=model_id or self.default_model_id, device=device, settings=made)


def _build_sam(scene, model_id, device, settings):
    from .sam import SamSegmenter

    return SamSegmenter.from_pretrained(model_id, device=device, settings=settings)


def _build_sam2(scene, model_id, device, settings):
    from .sam2 import Sam2Segmenter

    return Sam2Segmenter.from_pretrained(model_id, device=device, settings=settings)


def _build_classical(scene, model_id, device, settings):
    return ClassicalSegmenter(settings)


def _build_ground_truth(scene, model_id, device, settings):
    return GroundTruthSegmenter(scene)


SEGMENTERS: dict[str, SegmenterKind] = {
    kind.name: kind
    for kind in (
        SegmenterKind(
            "sam",
            _build_sam,
            settings="sam:SamSettings",
            default_model_id="facebook/sam-vit-huge",  # = sam.DEFAULT_SAM_MODEL
            description="SAM automatic masks (paper, default)",
            model_name="SAM",
            alternative="--segmenter classical",
        ),
        SegmenterKind(
            "sam2",
            _build_sam2,
            settings="sam2:Sam2Settings",
            default_model_id="facebook/sam2.1-hiera-tiny",  # = sam2.DEFAULT_SAM2_MODEL
            description="SAM 2.1 automatic masks, same settings (Hiera-tiny: lighter than SAM ViT-H)",
            model_name="SAM 2.1",
            alternative="--segmenter sam or --segmenter classical",
        ),
        SegmenterKind(
            "classical",
            _build_classical,
            settings="segmenters:ClassicalSettings",
            description="multi-scale Felzenszwalb (no weights needed)",
        ),
        SegmenterKind(
            "ground-truth",
            _build_ground_truth,
            needs_scene=True,
            description="demo scene regions with captions",
        ),
    )
}
SEGMENTER_NAMES = tuple(SEGMENTERS)


def locate_segmenter_model(name: str, model_id: Optional[str] = None):  # -> Optional[encoders.ModelLocation]
    """The model segmenter ``name`` would load (``model_id``, default its kind's), located
    without loading it (:func:`~.encoders.locate_pretrained`); None for a segmenter without one.
    A problem carries the advice loading it would give."""
    from .encoders import locate_pretrained, with_advice

    kind = SEGMENTERS.get(name)
    if kind is None or kind.default_model_id is None:
        return None
    found = locate_pretrained(model_id or kind.default_model_id, kind.model_name)
    return with_advice(found, kind.default_model_id, "--sam-model", kind.alternative)


def get_segmenter(
    name: str, scene=None, model_id: Optional[str] = None, device: str | torch.device = "cpu", **settings
):
    """Build a segmenter by name (see :data:`SEGMENTERS`): ``sam`` (``model_id`` default
    ``facebook/sam-vit-huge``, ``settings`` are :class:`SamSettings` fields), ``sam2`` (default
    ``facebook/sam2.1-hiera-tiny``, the same settings: :class:`Sam2Settings`), ``classical`` (:class:`ClassicalSettings`
    fields) or ``ground-truth`` (needs ``scene``)."""
    kind = SEGMENTERS.get(name)
    if kind is None:
        raise ValueError(f"unknown segmenter {name!r}; choose one of {', '.join(SEGMENTER_NAMES)}")
    return kind.create(scene=scene, model_id=model_id, device=device, **settings)
