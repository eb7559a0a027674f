"""Writing a demo scene as a normal scene folder (images, COLMAP text, ``transforms.json``, depth,
region ids, ``regions.json``, ``queries.json``, LangSplat labels, ``scene.json``)."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ...io import atomic_path, write_json, write_npy, write_png
from .. import labels as labels_mod
from .layouts import build_demo_scene, demo_cameras
from .model import GENERATOR, GENERATOR_VERSION, LAYOUTS, LEVELS, Region
from .shading import render_view


class _RegionStats:
    """Running sums for the covariance and bounding box of each region's surface points."""

    def __init__(self, num_regions: int) -> None:
        r = self.num_regions = num_regions
        self.count = np.zeros(r)  # [R]
        self.s1 = np.zeros((r, 3))  # [R, 3] sum of points
        self.s2 = np.zeros((r, 3, 3))  # [R, 3, 3] sum of outer products
        self.lo = np.full((r, 3), np.inf)  # [R, 3] bbox
        self.hi = np.full((r, 3), -np.inf)

    def add(
        self,
        regions: np.ndarray,  # [3, H, W]
        points: np.ndarray,  # [H, W, 3]
    ) -> None:
        pts = points.reshape(-1, 3)
        outer = (pts[:, :, None] * pts[:, None, :]).reshape(-1, 9)
        for level in range(regions.shape[0]):
            ids = regions[level].reshape(-1)
            ok = ids >= 0
            ids_ok, p_ok = ids[ok], pts[ok]
            r = self.num_regions
            self.count += np.bincount(ids_ok, minlength=r)
            for k in range(3):
                self.s1[:, k] += np.bincount(ids_ok, weights=p_ok[:, k], minlength=r)
            o = outer[ok]
            for k in range(9):
                self.s2[:, k // 3, k % 3] += np.bincount(ids_ok, weights=o[:, k], minlength=r)
            np.minimum.at(self.lo, ids_ok, p_ok)
            np.maximum.at(self.hi, ids_ok, p_ok)

    def extents(self) -> tuple[np.ndarray, np.ndarray]:
        """(largest covariance eigenvalue [R], bbox diagonal [R]); NaN for unseen regions."""
        cnt = np.maximum(self.count, 1)[:, None]
        mean = self.s1 / cnt
        cov = self.s2 / cnt[:, :, None] - mean[:, :, None] * mean[:, None, :]
        eig = np.linalg.eigvalsh(cov)[:, -1]
        diag = np.linalg.norm(self.hi - self.lo, axis=1)
        seen = self.count > 0
        return np.where(seen, np.maximum(eig, 0.0), np.nan), np.where(seen, diag, np.nan)


def _default_labelled_views(num_views: int) -> list[int]:
    step = max(1, num_views // 8)
    return list(range(step // 2, num_views, step))[:8]


def generate_demo_scene(
    out_dir: str | Path,
    *,
    num_views: int = 40,
    width: int = 160,
    height: int = 120,
    seed: int = 0,
    labelled_views: Optional[Sequence[int]] = None,
    supersample: int = 3,
    num_points: int = 4000,
    show_progress: bool = True,
    layout: str = "tabletop",
) -> Path:
    """Render the demo scene of ``layout`` (``LAYOUTS``) and write it as a normal scene folder (layout in
    docs/architecture.md): images, ``transforms.json``, COLMAP text, depth, region ids,
    ``regions.json``, ``queries.json``, LangSplat labels and ``scene.json``.

    Also writes ``points_source.npy`` (int32 [P, 3]: view index, row, column of the pixel
    centre each sparse point was traced from; sparse points are in COLMAP point-id order).

    Defaults: 40 views of 160x120, 3x3 supersampling, labels on 8 spread-out views, and every
    8th view (index % 8 == 0) held out for testing. Re-generating into a folder that holds a
    demo scene replaces it; any other non-empty folder is refused (InputError). ``scene.json``
    is written last: a folder without it is an interrupted generation. It records the
    ``layout`` (scenes written before layouts existed have none: they are tabletops).
    """
    from tqdm import tqdm

    from ..colmap import write_colmap_text
    from ..nerfstudio import write_transforms

    out = Path(out_dir)
    if num_views < 1 or width < 8 or height < 8:
        raise ValueError("the demo scene needs at least 1 view of at least 8x8 pixels")
    if layout not in LAYOUTS:
        raise ValueError(f"unknown demo layout {layout!r}; choose one of {', '.join(LAYOUTS)}")
    _prepare_output_dir(out)
    if labelled_views is None:
        labelled_views = _default_labelled_views(num_views)
    labelled_views = sorted({int(v) for v in labelled_views})
    if labelled_views and not (0 <= labelled_views[0] and labelled_views[-1] < num_views):
        raise ValueError(f"labelled views must be in [0, {num_views}), got {labelled_views}")
    start = time.perf_counter()

    scene = build_demo_scene(seed, layout)
    cameras = demo_cameras(num_views, width, height, seed, layout=layout)
    names = [labels_mod.frame_name(i) for i in range(num_views)]
    stats = _RegionStats(len(scene.regions))
    rng = np.random.default_rng([int(seed), 13])
    per_view = int(math.ceil(num_points / num_views))
    pts, cols, src = [], [], []
    labelled_regions = {}

    for i in tqdm(range(num_views), desc=f"rendering demo scene ({layout})", disable=not show_progress):
        view = render_view(scene, cameras[i], supersample=supersample, seed=seed)
        rgb8 = (np.clip(view.rgb, 0, 1) * 255.0 + 0.5).astype(np.uint8)
        write_png(out / "images" / f"{names[i]}.png", rgb8)
        write_npy(out / "depth" / f"{names[i]}.npy", view.depth.astype(np.float32))
        write_npy(out / "regions" / f"{names[i]}.npy", view.regions)
        stats.add(view.regions, view.points)
        pick = rng.choice(width * height, size=min(per_view, width * height), replace=False)
        rows, colsi = np.divmod(np.sort(pick), width)
        pts.append(view.points[rows, colsi])
        cols.append(rgb8[rows, colsi])
        src.append(np.stack([np.full_like(rows, i), rows, colsi], axis=1))
        if i in labelled_views:
            labelled_regions[i] = (view.regions, rgb8)

    points = np.concatenate(pts)[:num_points]
    colors = np.concatenate(cols)[:num_points]
    sources = np.concatenate(src)[:num_points].astype(np.int32)

    image_files = [f"{n}.png" for n in names]
    write_colmap_text(out / "sparse" / "0", cameras, image_files, points=points, colors=colors)
    write_transforms(
        out / "transforms.json", cameras, [f"images/{f}" for f in image_files], points=points, colors=colors
    )
    write_npy(out / "points_source.npy", sources)

    eig, diag = stats.extents()
    regions_json = {
        "levels": list(LEVELS),
        "extent_definition": "extent = extent_diag = bbox diagonal (m) of the region's surface points at the "
        "pixel centres of all views; extent_eig = largest eigenvalue (m^2) of their covariance",
        "regions": [
            {
                "id": r.id,
                "level": r.level,
                "name": r.name,
                "caption": r.caption,
                "parent": r.parent,
                "extent": _num(diag[r.id]),
                "extent_eig": _num(eig[r.id]),
                "extent_diag": _num(diag[r.id]),
                "pixels": int(stats.count[r.id]),
            }
            for r in scene.regions
        ],
    }
    write_json(out / "regions.json", regions_json)
    write_json(
        out / "queries.json",
        {"queries": [{"query": q.query, "type": q.type, "region_ids": list(q.region_ids)} for q in scene.queries]},
    )

    for i, (reg, rgb8) in labelled_regions.items():
        masks = {q.query: query_mask(reg, scene.regions, q.region_ids) for q in scene.queries}
        fl = labels_mod.labels_from_masks(names[i], masks)
        labels_mod.write_frame_labels(out / "label" / f"{names[i]}.json", fl)
        _write_jpeg(out / "label" / f"{names[i]}.jpg", rgb8)  # as in LangSplat's label folders

    write_json(
        out / "scene.json",
        {
            "generator": GENERATOR,
            "version": GENERATOR_VERSION,
            "layout": layout,
            "seed": int(seed),
            "num_views": num_views,
            "width": width,
            "height": height,
            "supersample": supersample,
            "camera_model": "PINHOLE",
            "up": [0.0, 0.0, 1.0],
            "depth": "z-depth (metres)",
            "test_views": [i for i in range(num_views) if i % 8 == 0],
            "labelled_views": labelled_views,
            "num_points": int(len(points)),
            "points_source": "points_source.npy",
        },
    )
    if show_progress:
        print(
            f"demo scene ({layout}): {num_views} views of {width}x{height} written to {out} "
            f"in {time.perf_counter() - start:.1f} s"
        )
    return out


# What a previous generation may have left (removed before writing a new scene there, so that
# no stale frame survives a smaller re-generation).
_OUTPUT_DIRS = ("images", "depth", "regions", "label", "sparse")
_OUTPUT_FILES = ("transforms.json", "sparse_pc.ply", "regions.json", "queries.json", "points_source.npy", "scene.json")


def _prepare_output_dir(out: Path) -> None:
    """Refuse a non-empty folder that is not a demo scene; clear an old demo scene's outputs.
    ``scene.json`` is written last, so a folder without it is an interrupted generation."""
    import shutil

    from ...errors import InputError
    from ..scene import SCENE_META_NAME, read_scene_meta

    if out.exists() and not out.is_dir():
        raise InputError(out, "output path exists and is not a folder")
    if not out.exists() or not any(out.iterdir()):
        return
    meta_path = out / SCENE_META_NAME
    is_demo = False
    if meta_path.is_file():
        try:
            is_demo = read_scene_meta(out).get("generator") == GENERATOR
        except InputError:
            is_demo = False
    else:  # an interrupted generation: only our own names inside
        names = {p.name for p in out.iterdir()}
        is_demo = names <= set(_OUTPUT_DIRS) | set(_OUTPUT_FILES)
    if not is_demo:
        raise InputError(out, "output folder is not empty and does not hold a demo scene; choose a new or empty folder")
    meta_path.unlink(missing_ok=True)  # first, so a crash below leaves an "interrupted" folder
    for name in _OUTPUT_DIRS:
        if (out / name).is_dir():
            shutil.rmtree(out / name)
    for name in _OUTPUT_FILES:
        (out / name).unlink(missing_ok=True)


def query_mask(
    regions: np.ndarray,  # [3, H, W] int32
    region_list: Sequence[Region] | Sequence[dict],
    region_ids: Sequence[int],
) -> np.ndarray:  # [H, W] bool
    """Union of the pixels of the given regions (each compared at its own level)."""
    level_of = {
        (r["id"] if isinstance(r, dict) else r.id): (r["level"] if isinstance(r, dict) else r.level)
        for r in region_list
    }
    mask = np.zeros(regions.shape[1:], dtype=bool)
    for rid in region_ids:
        mask |= regions[level_of[rid]] == rid
    return mask


def _num(x: float) -> Optional[float]:
    return None if not np.isfinite(x) else round(float(x), 6)


def _write_jpeg(path: Path, rgb8: np.ndarray) -> None:
    from PIL import Image

    with atomic_path(path) as tmp:
        Image.fromarray(rgb8).save(tmp, format="JPEG", quality=95)
