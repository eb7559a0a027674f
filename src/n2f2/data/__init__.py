"""Scene loading: every supported format becomes one :class:`~n2f2.data.scene.Scene`.

Formats (``load_scene(..., format=...)``):

* ``"nerfstudio"``: ``SCENE/transforms.json`` (or the path of any ``.json`` file);
  see :mod:`n2f2.data.nerfstudio`.
* ``"colmap"``: a COLMAP model in ``SCENE/sparse/0/`` (or ``SCENE/sparse/``, or ``SCENE`` itself
  being the model folder), binary preferred over text, with images in ``SCENE/images/``;
  see :mod:`n2f2.data.colmap`. Only ``sparse/0`` is read when COLMAP made several models.
* ``"auto"`` (default): nerfstudio when ``transforms.json`` exists, else COLMAP. A folder
  with both (the built-in demo scene writes both, describing the same cameras) loads
  ``transforms.json``; pass ``format="colmap"`` to read the COLMAP model instead.

Views are ordered by image path relative to the scene folder (for the usual flat
``images/`` folder that is sorted file-name order), so view index ``i`` is the same whatever
the format; this matches LangSplat's labels (``frame_00001`` is view 0).

Lens distortion (COLMAP ``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``, ``FULL_OPENCV`` and the
fisheye models; nerfstudio/instant-ngp ``k1 k2 k3 p1 p2`` and ``OPENCV_FISHEYE``) is removed
on load: each distorted view gets a pinhole camera and an undistorted PNG written once to a
cache outside the scene folder (``cache_dir``, else ``$N2F2_CACHE_DIR``, else
``~/.cache/n2f2``); see :mod:`n2f2.data.undistort`. Every later stage sees pinhole cameras
only; ``Scene.undistorted_from`` records the lens model and ``Scene.original_image_paths``
the user's files. Sparse points are 3D and stay as they are.

``downscale`` works like 3DGS ``-r``: cameras become :meth:`Camera.downscaled(factor)
<n2f2.cameras.Camera.downscaled>` (``round(W / factor)`` pixels, intrinsics scaled with the
pixel-centre convention) and images are resized when loaded. It applies after
undistortion. For an integer factor, a pre-downscaled sibling folder such as ``images_2/``
(written by 3DGS ``convert.py --resize`` and ``ns-process-data``) is used instead when it
holds every image and no view is distorted (those copies are distorted too).

Everything that can be checked without decoding pixels is checked at load time: every
listed image must exist (else one error naming the missing ones; ``skip_missing=True`` drops
those views with a warning) and have the camera's aspect ratio, so a bad scene fails at once
with an :class:`~n2f2.errors.InputError` naming the file rather than in the middle of training.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import numpy as np

from ..errors import InputError
from .scene import GroundTruth, Scene, keep_present_images, load_image, relative_name

__all__ = ["FORMATS", "GroundTruth", "Scene", "detect_format", "load_image", "load_scene"]

FORMATS = ("auto", "colmap", "nerfstudio")


def _colmap_model_dir(path: Path) -> Optional[Path]:
    from .colmap import find_model_files

    for candidate in (path / "sparse" / "0", path / "sparse", path):
        if candidate.is_dir() and find_model_files(candidate) is not None:
            return candidate
    return None


def detect_format(path: str | Path, format: str = "auto") -> tuple[str, Path]:
    """``("nerfstudio", transforms_json)`` or ``("colmap", model_dir)`` for scene ``path``."""
    from .nerfstudio import TRANSFORMS_NAME, transforms_path

    path = Path(path)
    if format not in FORMATS:
        raise InputError(None, f"unknown scene format {format!r}; expected one of {', '.join(FORMATS)}")
    if not path.exists():
        raise InputError(path, "scene path does not exist")
    if format == "nerfstudio" or (
        format == "auto" and (path.suffix.lower() == ".json" or (path / TRANSFORMS_NAME).is_file())
    ):
        json_path = transforms_path(path)
        if not json_path.is_file():
            raise InputError(json_path, "file does not exist (a nerfstudio scene needs transforms.json)")
        return "nerfstudio", json_path
    model = _colmap_model_dir(path) if path.is_dir() else None
    if model is None:
        if format == "colmap":
            raise InputError(
                path / "sparse" / "0",
                "no COLMAP model found: expected cameras.bin + images.bin (or cameras.txt + images.txt)",
            )
        raise InputError(
            path,
            f"no scene found: expected {TRANSFORMS_NAME} (nerfstudio) or sparse/0/ "
            f"with cameras.bin|txt and images.bin|txt (COLMAP)",
        )
    return "colmap", model


def _colmap_root(model: Path) -> Path:
    """The scene folder of a COLMAP model folder: the nearest ancestor holding ``images/``."""
    for candidate in (model.parent.parent, model.parent, model):
        if (candidate / "images").is_dir():
            return candidate
    return model.parent.parent if model.parent.name == "sparse" else model.parent


def load_scene(
    path: str | Path,
    downscale: float = 1,
    format: str = "auto",
    *,
    cache_dir: Optional[str | Path] = None,
    skip_missing: bool = False,
) -> Scene:
    """Load a scene folder (COLMAP or nerfstudio, see the module docstring) into a Scene.

    ``downscale`` (>= 1 usually, like 3DGS ``-r``) divides the image size; ``format`` is
    ``"auto"``, ``"colmap"`` or ``"nerfstudio"``. Distorted views are undistorted into
    ``cache_dir`` (default ``$N2F2_CACHE_DIR`` or ``~/.cache/n2f2``). Views whose image is
    missing are an error, or dropped with a warning when ``skip_missing``. Sets
    ``scene.ground_truth`` when the folder has ``regions.json`` (the built-in demo scene).
    Bad input raises :class:`InputError`.
    """
    from .undistort import undistort_views

    downscale = float(downscale)
    if not np.isfinite(downscale) or downscale <= 0:
        raise InputError(None, f"downscale factor must be a positive number, got {downscale}")
    kind, source = detect_format(path, format)

    if kind == "nerfstudio":
        from .nerfstudio import read_transforms

        data = read_transforms(source, missing="skip" if skip_missing else "error")
        root = source.parent
        cameras, lenses, image_paths = data.cameras, data.lenses, data.image_paths
        points, colors = data.points, data.colors
        source_format, listing = "nerfstudio", source
    else:
        from .colmap import read_colmap_scene

        model = read_colmap_scene(source)
        root = _colmap_root(source)
        cameras, lenses, points, colors = model.cameras, model.lenses, model.points, model.colors
        image_paths = [root / "images" / name for name in model.image_names]
        source_format, listing = f"colmap-{model.kind}", model.files["images"]
        keep = keep_present_images(image_paths, listing, root, skip_missing)
        cameras = [cameras[i] for i in keep]
        lenses = [lenses[i] for i in keep]
        image_paths = [image_paths[i] for i in keep]

    order = sorted(range(len(image_paths)), key=lambda i: relative_name(image_paths[i], root))
    cameras = [cameras[i] for i in order]
    lenses = [lenses[i] for i in order]
    image_paths = [image_paths[i] for i in order]
    seen: dict[str, int] = {}
    for k, path in enumerate(image_paths):  # the same file under two names (./a/../a/x.png, a link) too
        first = image_paths[seen.setdefault(os.path.realpath(path), k)]
        if seen[os.path.realpath(path)] != k:
            alias = "" if first == path else f" (also as {relative_name(first, root)})"
            raise InputError(listing, f"image {relative_name(path, root)} is listed twice{alias}")

    distorted = [lens for lens in lenses if lens is not None and not lens.is_pinhole]
    original_paths, undistorted_from = None, None
    if distorted:
        # Check the user's files (so errors name them) before spending time undistorting.
        _check_aspect_ratios(cameras, image_paths, listing)
        original_paths = image_paths
        cameras, image_paths = undistort_views(cameras, lenses, image_paths, cache_dir, listing)
        undistorted_from = ", ".join(sorted({lens.name for lens in distorted}))
    if downscale != 1:
        cameras = [c.downscaled(downscale) for c in cameras]
        if not distorted:
            image_paths = _predownscaled(image_paths, downscale)
    _check_aspect_ratios(cameras, image_paths, listing)

    scene = Scene(
        root=root,
        cameras=cameras,
        image_paths=image_paths,
        points=points,
        point_colors=colors,
        downscale=downscale,
        source_format=source_format,
        undistorted_from=undistorted_from,
        original_image_paths=original_paths,
    )
    if (root / "regions.json").is_file():
        scene.ground_truth = GroundTruth(root, scene.image_names)
    return scene


def _predownscaled(image_paths: list[Path], factor: float) -> list[Path]:
    """``images_N/<name>`` for every image when ``factor`` is an integer N and all exist."""
    if factor != int(factor) or factor <= 1:
        return image_paths
    n = int(factor)
    candidates = [p.parent.with_name(f"{p.parent.name}_{n}") / p.name for p in image_paths]
    return candidates if all(c.is_file() for c in candidates) else image_paths


def _check_aspect_ratios(cameras, image_paths: list[Path], listing: Path) -> None:
    """Read each image header (not its pixels) and reject one whose aspect ratio differs
    from its camera's: resizing it would silently distort the image."""
    from .scene import open_image

    for cam, image_path in zip(cameras, image_paths):
        with open_image(image_path) as im:
            w, h = im.size
        # Rounding to whole pixels moves a side by at most one pixel of the image (images_2
        # written with floor instead of round) plus one pixel of the camera, which is
        # w / cam.width image pixels when the camera is downscaled; more is another shape.
        tol = 1.0 + max(w / cam.width, h / cam.height) + 1e-9
        if abs(h - w * cam.height / cam.width) > tol and abs(w - h * cam.width / cam.height) > tol:
            raise InputError(
                image_path,
                f"image is {w}x{h} pixels but the camera in {listing.name} is "
                f"{cam.width}x{cam.height} (after downscaling): a different aspect ratio",
            )
