"""One in-memory description of a posed image collection, whatever format it came from.

Images are ordered by file name (sorted), so view index i is the same for every loader and
matches LangSplat's label convention (``frame_00001`` is index 0).
"""

from __future__ import annotations

import contextlib
import struct
import sys
import warnings
import zlib
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Iterator, Optional, Sequence

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
            self._cache[index] = load_image(
                self.image_paths[index], self.cameras[index].width, self.cameras[index].height
            )
        return self._cache[index]

    def scene_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounds [3], [3] of the sparse points, or of the camera centres."""
        pts = (
            self.points if self.points is not None and len(self.points) else np.stack([c.center for c in self.cameras])
        )
        return pts.min(axis=0), pts.max(axis=0)

    def extent(self) -> float:
        """Scene extent as 3DGS defines it: 1.1 x the largest camera distance from their mean."""
        centers = np.stack([c.center for c in self.cameras])
        return float(1.1 * np.linalg.norm(centers - centers.mean(axis=0), axis=1).max())


def keep_present_images(
    image_paths: Sequence[Path], listing: Path, root: Path, skip_missing: bool = False
) -> list[int]:
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
        raise InputError(
            listing,
            f"{n} of the {total} images it lists {verb} not exist: {names} (--skip-missing loads the other views)",
        )
    print(
        f"warning: skipping {n} of {total} views listed in {listing.name} whose images do not exist: {names}",
        file=sys.stderr,
    )
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

    def depth_path(self, index: int) -> Path:
        return self.root / "depth" / f"{self.image_names[index]}.npy"

    def depth(self, index: int) -> np.ndarray:
        """float32 [H, W] z-depth at full resolution."""
        return np.load(self.depth_path(index))

    def views_with_depth(self, views: Sequence[int], what: str = "") -> list[int]:
        """The ``views`` whose depth file exists. Depth is optional ground truth: the missing
        files are named in one warning line on stderr (``what`` says which metric goes without
        them), not an error."""
        missing = [i for i in views if not self.depth_path(i).is_file()]
        if missing:
            shown = ", ".join(f"depth/{self.image_names[i]}.npy" for i in missing[:MISSING_NAMES_SHOWN])
            more = f" and {len(missing) - MISSING_NAMES_SHOWN} more" if len(missing) > MISSING_NAMES_SHOWN else ""
            print(
                f"warning: {self.root}: {shown}{more} missing; {what or 'depth metrics'} skip "
                f"{'that view' if len(missing) == 1 else 'those views'}",
                file=sys.stderr,
            )
        return [i for i in views if i not in missing]

    def region_ids(self, index: int) -> np.ndarray:
        """int32 [L, H, W] region id per level (levels listed in regions.json), -1 = none."""
        return np.load(self.root / "regions" / f"{self.image_names[index]}.npy")

    @property
    def regions(self) -> dict:
        return _read_json(self.root / "regions.json")

    @property
    def queries(self) -> list[dict]:
        return _read_json(self.root / "queries.json")["queries"]


SCENE_META_NAME = "scene.json"


def read_scene_meta(root: str | Path) -> dict:
    """``ROOT/scene.json`` (the demo generator's record: layout, seed, sizes, held-out and
    labelled views), or ``{}`` when the scene has none. Not a JSON object: InputError."""
    import json

    path = Path(root) / SCENE_META_NAME
    if not path.is_file():
        return {}
    try:
        meta = json.loads(path.read_text())
    except (OSError, ValueError):
        raise InputError(path, "not a valid JSON object") from None
    if not isinstance(meta, dict):
        raise InputError(path, "not a valid JSON object")
    return meta


def _read_json(path: Path) -> dict:
    # Keyed on the modification time too, so a scene regenerated in place is read again.
    return _read_json_cached(str(path), path.stat().st_mtime_ns)


@lru_cache(maxsize=16)
def _read_json_cached(path: str, mtime_ns: int) -> dict:
    import json

    return json.loads(Path(path).read_text())


@contextlib.contextmanager
def open_image(path: Path) -> Iterator[Any]:
    """The PIL image of ``path``, its header read and its pixels not yet decoded. A file PIL
    cannot identify, and a header declaring more pixels than PIL decodes safely (twice
    ``Image.MAX_IMAGE_PIXELS``: a decompression bomb), are an :class:`InputError` naming it."""
    from PIL import Image, UnidentifiedImageError

    try:
        with warnings.catch_warnings():
            # Between one and two times the limit PIL only warns; such images are read.
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            im = Image.open(path)
    except Image.DecompressionBombError as e:
        raise InputError(path, f"image is too large to decode safely ({e})") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise InputError(path, f"cannot read image ({e})") from None
    with im:
        yield im


# Errors PIL and OpenCV raise for corrupt pixel data (truncated files, bad checksums, ...).
_DECODE_ERRORS = (OSError, SyntaxError, ValueError, EOFError, struct.error, zlib.error)


def load_image(path: Path, width: int, height: int) -> np.ndarray:
    """float32 [H, W, 3] in [0, 1] of the image file, resized to ``width`` x ``height``. 8-bit
    images are divided by 255, 16-bit ones (grayscale or colour PNG, 16-bit TIFF) by 65535;
    grayscale becomes three equal channels, alpha is dropped."""
    from PIL import Image

    if not path.is_file():
        raise InputError(path, "image listed by the scene file does not exist")
    with open_image(path) as im:
        try:
            if _is_16bit(im, path):
                arr = _read_16bit(im, path)
                if arr.shape[:2] != (height, width):
                    # Pillow puts its filter names into the module at import; Image.Resampling needs Pillow 9.1.
                    resample = Image.BICUBIC if width < arr.shape[1] else Image.BILINEAR  # pyright: ignore[reportAttributeAccessIssue]
                    arr = _resize_float(arr, width, height, resample)
            else:
                im = im.convert("RGB")
                if im.size != (width, height):
                    resample = Image.BICUBIC if width < im.size[0] else Image.BILINEAR  # pyright: ignore[reportAttributeAccessIssue]
                    im = im.resize((width, height), resample)
                arr = np.asarray(im, dtype=np.float32) / 255.0
        except Image.DecompressionBombError as e:
            raise InputError(path, f"image is too large to decode safely ({e})") from None
        except _DECODE_ERRORS as e:
            raise InputError(path, f"cannot read image ({e})") from None
    if arr.size == 0:
        raise InputError(path, "image is empty")
    return arr


_GRAY16_MODES = ("I;16", "I;16L", "I;16B", "I;16N", "I")


def _is_16bit(im: Any, path: Path) -> bool:
    """16 bits per sample: PIL's 16-bit grayscale modes, a PNG whose header says bit depth 16,
    or a TIFF of unsigned 16-bit samples (PIL reads 16-bit colour PNGs and TIFFs as 8-bit RGB,
    dropping the low byte)."""
    if im.mode in _GRAY16_MODES:
        return True
    if im.format == "PNG":
        with open(path, "rb") as f:
            head = f.read(26)  # signature (8), IHDR length + type (8), width, height, bit depth, colour type
        return len(head) == 26 and head[12:16] == b"IHDR" and head[24] == 16
    if im.format == "TIFF":
        tags = getattr(im, "tag_v2", {})
        bits, sample_format = tags.get(258), tags.get(339, 1)  # BitsPerSample, SampleFormat (1 = unsigned)
        bits = bits if isinstance(bits, tuple) else (bits,)
        sample_format = sample_format if isinstance(sample_format, tuple) else (sample_format,)
        return all(b == 16 for b in bits) and all(f == 1 for f in sample_format)
    return False


def _read_16bit(im: Any, path: Path) -> np.ndarray:  # -> float32 [h, w, 3] in [0, 1]
    if im.mode in _GRAY16_MODES:
        gray = np.asarray(im).astype(np.float32)
        if im.mode == "I":  # 32-bit integers holding 16-bit samples
            gray = np.clip(gray, 0.0, 65535.0)
        return np.repeat((gray / 65535.0)[..., None], 3, axis=2)
    import cv2

    data = np.fromfile(path, dtype=np.uint8)
    pixels = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if pixels is None or pixels.dtype != np.uint16:
        raise OSError(f"OpenCV cannot decode this 16-bit {im.format or 'image'}")
    if pixels.ndim == 2:
        pixels = np.repeat(pixels[..., None], 3, axis=2)
    elif pixels.shape[2] <= 2:  # gray (+ alpha)
        pixels = np.repeat(pixels[..., :1], 3, axis=2)
    else:  # OpenCV's BGR (+ alpha)
        pixels = pixels[..., 2::-1]
    return np.ascontiguousarray(pixels, dtype=np.float32) / 65535.0


def _resize_float(
    image: np.ndarray,  # [h, w, 3] float32 in [0, 1]
    width: int,
    height: int,
    resample: int,
) -> np.ndarray:  # -> [height, width, 3]
    """The 8-bit path's PIL filter, applied per channel in float (PIL mode "F"), kept in [0, 1]."""
    from PIL import Image

    channels = [
        np.asarray(Image.fromarray(np.ascontiguousarray(image[..., c]), mode="F").resize((width, height), resample))
        for c in range(image.shape[2])
    ]
    return np.clip(np.stack(channels, axis=2), 0.0, 1.0).astype(np.float32)
