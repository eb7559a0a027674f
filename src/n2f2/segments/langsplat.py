"""Import LangSplat's preprocessed segments and CLIP features (``language_features/``), so users
of LangSplat's ``preprocess.py`` can train N2F2 without re-running SAM and CLIP.

Per image ``<stem>``, LangSplat writes:

* ``<stem>_s.npy``: int (stored as float) ``[4, H, W]``, one segment map per level
  (0 = default, 1 = s, 2 = m, 3 = l). Values are *global* row indices into ``_f.npy``: level
  j's local mask index plus the number of masks of the levels before it; -1 = no mask.
* ``<stem>_f.npy``: float ``[N, E]`` L2-normalised CLIP ViT-B/16 (laion2b_s34b_b88k) image
  embeddings, the rows of all levels concatenated.

So the four levels are exactly the bank's non-overlapping layers, and the global row index is
the bank's local segment id.
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import InputError
from .encoders import DEFAULT_CLIP_MODEL
from .segmenters import SegmentSet, segment_layers

LANGSPLAT_LEVELS = ("default", "s", "m", "l")


def _load(path: Path) -> np.ndarray:
    if not path.is_file():
        raise InputError(path, "LangSplat feature file does not exist (run LangSplat's preprocess.py, "
                         "or point --features at its language_features folder)")
    try:
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise InputError(path, f"cannot read .npy file ({e})") from None


def read_langsplat(features_dir: str | Path, stem: str,
                   height: Optional[int] = None, width: Optional[int] = None) -> tuple[np.ndarray, np.ndarray]:
    """Read and check one image's LangSplat files.

    Returns ``(layers [4, H, W] int32, -1 = none; embeddings [N, E] float32)``. Raises
    :class:`InputError` naming the file when the maps are not ``[levels, H, W]`` of the expected
    image size, hold non-integers or indices outside ``[-1, N)``, or when a row index appears
    in two levels."""
    features_dir = Path(features_dir)
    s_path, f_path = features_dir / f"{stem}_s.npy", features_dir / f"{stem}_f.npy"
    seg = _load(s_path)
    feats = _load(f_path)
    if feats.ndim != 2:
        raise InputError(f_path, f"expected features [N, E], got shape {feats.shape}")
    if not np.issubdtype(feats.dtype, np.floating):
        raise InputError(f_path, f"expected float features, got {feats.dtype}")
    if seg.ndim == 2:
        seg = seg[None]
    if seg.ndim != 3 or seg.shape[1] == 0 or seg.shape[2] == 0:
        raise InputError(s_path, f"expected segment maps [levels, H, W], got shape {seg.shape}")
    if height is not None and width is not None and seg.shape[1:] != (height, width):
        raise InputError(s_path, f"segment maps are {seg.shape[2]}x{seg.shape[1]} but the image is "
                         f"{width}x{height} (use --downscale so the scene matches LangSplat's resolution)")
    if np.issubdtype(seg.dtype, np.floating):
        if not np.isfinite(seg).all() or (seg != np.round(seg)).any():
            raise InputError(s_path, "segment maps hold non-integer values")
    layers = seg.astype(np.int64)
    n = feats.shape[0]
    if layers.size and (layers.min() < -1 or layers.max() >= n):
        raise InputError(s_path, f"segment index {int(layers.max()) if layers.max() >= n else int(layers.min())} "
                         f"is outside [-1, {n}): {f_path.name} has only {n} rows")
    try:
        segment_layers(layers.astype(np.int32), n)
    except ValueError as e:
        raise InputError(s_path, f"not LangSplat's level layout: {e}") from None
    return layers.astype(np.int32), np.asarray(feats, dtype=np.float32)


class LangSplatSource:
    """Segments + embeddings of one view from LangSplat files (a bank ``source``)."""

    name = "langsplat"

    def __init__(self, features_dir: str | Path, encoder_spec: Optional[dict] = None) -> None:
        self.features_dir = Path(features_dir)
        if not self.features_dir.is_dir():
            raise InputError(self.features_dir, "LangSplat features folder does not exist")
        # The features are OpenCLIP ViT-B/16 laion2b_s34b_b88k; queries need that text encoder.
        self.encoder_spec = dict(encoder_spec or {"name": "clip", "model_id": DEFAULT_CLIP_MODEL})
        self.encoder_spec.setdefault("description",
                                     "LangSplat language_features (OpenCLIP ViT-B/16 laion2b_s34b_b88k "
                                     "image embeddings of SAM masks); queries through the CLIP text encoder")
        self._dim: Optional[int] = None

    def prepare(self, stems: list[str]) -> None:
        """Learn the embedding width from the first image's ``_f.npy`` (memory-mapped), so
        ``bank.json`` can name it before extraction starts."""
        if stems:
            path = self.features_dir / f"{stems[0]}_f.npy"
            _load(path)  # existence / readability, with a clear error
            feats = np.load(path, mmap_mode="r")
            if feats.ndim != 2:
                raise InputError(path, f"expected features [N, E], got shape {feats.shape}")
            self._set_dim(int(feats.shape[1]), path)

    def _set_dim(self, dim: int, path: Path) -> None:
        if self._dim is None:
            want = self.encoder_spec.get("embed_dim")
            if want is not None and int(want) != dim:
                raise InputError(path, f"features are {dim}-d, the encoder makes {want}-d embeddings")
            self._dim = dim
            self.encoder_spec["embed_dim"] = dim
        elif dim != self._dim:
            raise InputError(path, f"features are {dim}-d, earlier images had {self._dim}-d")

    @property
    def segmenter_spec(self) -> dict:
        return {"name": "langsplat", "features": str(self.features_dir), "levels": list(LANGSPLAT_LEVELS)}

    def extract(self, index: int, stem: str, image: np.ndarray) -> tuple[SegmentSet, np.ndarray]:
        H, W = image.shape[:2]
        layers, feats = read_langsplat(self.features_dir, stem, H, W)
        self._set_dim(int(feats.shape[1]), self.features_dir / f"{stem}_f.npy")
        return SegmentSet(layers, np.ones(feats.shape[0], np.float32)), feats
