"""One in-memory description of a posed image collection, whatever format it came from.

Images are ordered by file name (sorted), so view index i is the same for every loader and
matches LangSplat's label convention (``frame_00001`` is index 0).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..cameras import Camera
from ..errors import InputError

# Missing images named in an error or warning before "and N more".
MISSING_NAMES_SHOWN = 5


@dataclass
class Scene:
    """Cameras, lazily loaded images, optional sparse points and optional ground truth.

    ``cameras[i]`` already accounts for ``downscale``; :meth:`image` returns the image resized
    to that camera's size. Cameras are always pinhole: views with lens distortion were
    undistorted on load, and then ``image_paths[i]`` is the undistorted copy in the cache,
    ``original_image_paths[i]`` the user's file and ``undistorted_from`` names the lens
    model(s) (see :mod:`n2f2.data.undistort`).
    """

    root: Path
    cameras: list[Camera]
    image_paths: list[Path]
    points: Optional[np.ndarray] = None  # [P, 3] float64 world-space sparse points
    point_colors: Optional[np.ndarray] = None  # [P, 3] uint8
    downscale: float = 1.0
    source_format: str = ""  # "colmap-binary", "colmap-text", "nerfstudio"
    ground_truth: Optional["GroundTruth"] = None
    undistorted_from: Optional[str] = None  # e.g. "COLMAP OPENCV"; None when no view was distorted
    original_image_paths: Optional[list[Path]] = None  # the user's images, when some were undistorted
    _cache: dict = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if len(self.cameras) != len(self.image_paths):
            raise ValueError("scene needs one camera per image")
        if self.original_image_paths is not None and len(self.original_image_paths) != len(self.image_paths):
            raise ValueError("scene needs one original image path per image")

    @property
    def num_undistorted(self) -> int:
        """How many views were undistorted on load."""
        if self.original_image_paths is None:
            return 0
        return sum(a != b for a, b in zip(self.image_paths, self.original_image_paths))

    def __len__(self) -> int:
        return len(self.cameras)

    @property
    def image_names(self) -> list[str]:
        """File stems, e.g. ``frame_00001``."""
        return [p.stem for p in self.image_paths]

    def image(self, index: int) -> np.ndarray:
        """float32 [H, W, 3] in [0, 1], resized to ``cameras[index]``'s size. Loaded on demand."""
        if not 0 <= index < len(self):
            raise IndexError(f"view index {index} out of range (scene has {len(self)} views)")
        if index not in self._cache:
            self._cache[index] = load_image(self.image_paths[index], self.cameras[index].width,
                                            self.cameras[index].height)
        return self._cache[index]

    def check_images_exist(self) -> None:
        """Fail early, naming the file, when an image listed by the scene file is missing."""
        for path in self.image_paths:
            if not path.is_file():
                raise InputError(path, "image listed by the scene file does not exist")

    def scene_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds [3], [3] of the sparse points, or of the camera centres."""
        pts = self.points if self.points is not None and len(self.points) else np.stack(
            [c.center for c in self.cameras])
        return pts.min(axis=0), pts.max(axis=0)

    def extent(self) -> float:
        """Scene extent as 3DGS defines it: 1.1 x the largest camera distance from their mean."""
        centers = np.stack([c.center for c in self.cameras])
        return float(1.1 * np.linalg.norm(centers - centers.mean(axis=0), axis=1).max())


def keep_present_images(image_paths: Sequence[Path], listing: Path, root: Path,
                        skip_missing: bool = False) -> list[int]:
    """Indices of the views whose image file exists. When some are missing: one
    :class:`InputError` on ``listing`` naming how many and which, or, with ``skip_missing``,
    one warning line on stderr and the rest are kept (all missing is still an error)."""
    present = [i for i, p in enumerate(image_paths) if p.is_file()]
    missing = [image_paths[i] for i in sorted(set(range(len(image_paths))) - set(present))]
    if not missing:
        return present
    shown = sorted(relative_name(p, root) for p in missing)
    names = ", ".join(shown[:MISSING_NAMES_SHOWN])
    if len(shown) > MISSING_NAMES_SHOWN:
        names += f" and {len(shown) - MISSING_NAMES_SHOWN} more"
    n, total = len(missing), len(image_paths)
    if not present:
        raise InputError(listing, f"none of the {total} images it lists exists: {names}")
    if not skip_missing:
        verb = "does" if n == 1 else "do"
        raise InputError(listing, f"{n} of the {total} images it lists {verb} not exist: {names} "
                                  f"(--skip-missing loads the other views)")
    print(f"warning: skipping {n} of {total} views listed in {listing.name} whose images do not exist: {names}",
          file=sys.stderr)
    return present


def relative_name(path: Path, root: Path) -> str:
    """``path`` relative to ``root`` in POSIX form (the view-order key), or ``path`` itself."""
    try:
        return path.relative_to(root).as_posix()
    except ValueError:
        return path.as_posix()


@dataclass
class GroundTruth:
    """Exact ground truth that the built-in synthetic scene writes (see ``data.synthetic``)."""

    root: Path
    image_names: list[str]

    def depth(self, index: int) -> np.ndarray:
        """float32 [H, W] z-depth at full resolution."""
        return np.load(self.root / "depth" / f"{self.image_names[index]}.npy")

    def region_ids(self, index: int) -> np.ndarray:
        """int32 [L, H, W] region id per level (levels listed in regions.json), -1 = none."""
        return np.load(self.root / "regions" / f"{self.image_names[index]}.npy")

    @property
    def regions(self) -> dict:
        return _read_json(self.root / "regions.json")

    @property
    def queries(self) -> list[dict]:
        return _read_json(self.root / "queries.json")["queries"]


def _read_json(path: Path) -> dict:
    # Keyed on the modification time too, so a scene regenerated in place is read again.
    return _read_json_cached(str(path), path.stat().st_mtime_ns)


@lru_cache(maxsize=16)
def _read_json_cached(path: str, mtime_ns: int) -> dict:
    import json

    return json.loads(Path(path).read_text())


def load_image(path: Path, width: int, height: int) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise InputError(path, "image listed by the scene file does not exist")
    try:
        with Image.open(path) as im:
            im = im.convert("RGB")
            if im.size != (width, height):
                im = im.resize((width, height), Image.BICUBIC if width < im.size[0] else Image.BILINEAR)
            arr = np.asarray(im, dtype=np.float32) / 255.0
    except (UnidentifiedImageError, OSError) as e:
        raise InputError(path, f"cannot read image ({e})") from None
    if arr.size == 0:
        raise InputError(path, "image is empty")
    return arr
