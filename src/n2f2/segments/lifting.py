"""Lift segments to 3D and measure their physical scale (paper Sec. 3.2, following GARField).

Each segment's pixels are unprojected with the view's depth (the fitted 3DGS's expected depth,
or the demo scene's exact depth with ``--depth-source gt``); its scale is the largest
eigenvalue of the covariance of those 3D points (the paper), with ``scale_measure="extent"``
the squared diagonal of their robust oriented box, or with ``scale_measure="area"`` the surface
the pixels cover at their depth (units: scene length squared). The mask is eroded once with a
3 x 3 kernel first, so pixels on depth discontinuities at the segment's boundary (which belong
to the background as often as to the segment) do not inflate it.

Everything works on the bank's non-overlapping id layers: per layer, one ``np.bincount`` per
moment gives the point count, sums and second moments of every segment at once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, ClassVar, Optional

import numpy as np

from ..cameras import Camera
from ..config import PRESET_NAMES, ConfigDict, option
from ..errors import InputError

SCALE_DESCRIPTIONS = {  # LiftSettings.scale_measure -> what bank.json records
    "eigenvalue": "largest eigenvalue of the covariance of the lifted points (length^2)",
    "extent": "squared diagonal of the robust oriented box of the lifted points (length^2)",
    "area": "visible surface of the lifted pixels, each pixel's footprint z^2 / (fx fy) summed (length^2)",
}
SCALE_MEASURES = tuple(SCALE_DESCRIPTIONS)

# A depth provider returns, for view i, z-depth [H, W] and a validity mask [H, W].
DepthProvider = Callable[[int], tuple[np.ndarray, np.ndarray]]


@dataclass
class LiftSettings(ConfigDict):
    PRESETS: ClassVar[tuple[str, ...]] = PRESET_NAMES  # see the static methods of those names

    erode: bool = True  # erode each mask once with a 3 x 3 kernel before lifting (GARField)
    min_points: int = 10  # fewer valid 3D points -> degenerate segment (scale NaN, dropped)
    min_alpha: float = 0.5  # rendered pixels with less accumulated opacity have no depth
    # Robust depth: drop a segment's pixels whose depth is more than ``outlier_mads`` scaled
    # median absolute deviations (1.4826 MAD ~ one standard deviation) from the segment's
    # median depth, and at least ``outlier_min_rel`` x median depth away. A few pixels with
    # background depth (3DGS depth blurs across occlusion edges; masks overshoot) otherwise
    # dominate the covariance of a small segment. None disables it.
    outlier_mads: Optional[float] = 3.0
    outlier_min_rel: float = 0.02
    # How a segment's lifted points become one scale (only their order matters: scales are
    # quantile-binned). "eigenvalue" (paper): largest eigenvalue of their covariance.
    # "extent" (not in the paper): squared diagonal of their robust oriented box, the
    # [p, 100 - p] percentile range (p = extent_percentile) along each principal axis. "area"
    # (not in the paper): the sum of the lifted pixels' footprints z^2 / (fx fy), the surface
    # the segment shows in that view. A part's mask lies inside its parent's, so by area it is
    # never the larger (erosion and outlier rejection aside); the eigenvalue and the extent put
    # a segment below one of its parts in some (view, parent, part) triples, and give a thin
    # part (a frame, a wheel) its parent's scale (docs/measurements.md, "Segment scale by
    # visible area").
    scale_measure: str = option(
        "eigenvalue",
        help="segment scale from its lifted 3D points: eigenvalue = largest eigenvalue of their covariance "
        "(paper); extent = squared diagonal of their robust oriented box, a percentile range along each "
        "principal axis; area = the surface its pixels cover at their depth, never more than its parent's "
        "(extent and area: not in the paper)",
        choices=SCALE_MEASURES,
    )
    extent_percentile: float = 2.0

    @staticmethod
    def cpu() -> "LiftSettings":
        """Segments measured by their visible area (never larger than their parent's)."""
        return LiftSettings(scale_measure="area")

    @staticmethod
    def paper() -> "LiftSettings":
        """The paper's largest eigenvalue."""
        return LiftSettings()

    def __post_init__(self) -> None:
        if self.scale_measure not in SCALE_MEASURES:
            raise ValueError(f"scale_measure must be one of {SCALE_MEASURES}, got {self.scale_measure!r}")
        if not 0.0 <= self.extent_percentile < 50.0:
            raise ValueError(f"extent_percentile must be in [0, 50), got {self.extent_percentile}")


def erode_layers(layers: np.ndarray) -> np.ndarray:  # [L, H, W] int -> [L, H, W] int32
    """Erode every segment of every id layer with a 3 x 3 square kernel, as ``cv2.erode`` does
    on each segment's binary mask (pixels outside the image count as inside the mask).

    A pixel keeps its id iff all 8 neighbours carry the same id. Replicate-padding the border
    equals ignoring out-of-image neighbours, which is cv2's default border for erosion."""
    layers = np.asarray(layers, dtype=np.int32)
    if layers.size == 0:
        return layers.copy()
    padded = np.pad(layers, ((0, 0), (1, 1), (1, 1)), mode="edge")
    H, W = layers.shape[1:]
    same = np.ones(layers.shape, dtype=bool)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            same &= padded[:, dy : dy + H, dx : dx + W] == layers
    return np.where(same, layers, -1).astype(np.int32)


def _counts(layers: np.ndarray, valid: np.ndarray, S: int) -> np.ndarray:
    """[S] number of valid pixels of each segment."""
    ids = layers[:, valid]
    return np.bincount(ids[ids >= 0], minlength=S)[:S]


def segment_quantiles(
    ids: np.ndarray,  # [P] segment id of each sample (>= 0)
    values: np.ndarray,  # [P]
    S: int,
    q: float,
) -> np.ndarray:
    """[S] ``q``-quantile (0..1, linear interpolation as ``np.quantile``) of ``values`` per
    segment (NaN for segments without samples), by one lexicographic sort instead of a loop
    over segments."""
    out = np.full(S, np.nan)
    if ids.size == 0:
        return out
    order = np.lexsort((values, ids))
    v = values[order]
    counts = np.bincount(ids, minlength=S)[:S]
    starts = np.cumsum(counts) - counts
    has = counts > 0
    pos = q * (counts[has] - 1)
    lo = np.floor(pos).astype(np.int64)
    hi = np.ceil(pos).astype(np.int64)
    frac = pos - lo
    out[has] = (1 - frac) * v[starts[has] + lo] + frac * v[starts[has] + hi]
    return out


def segment_medians(
    ids: np.ndarray,  # [P] segment id of each sample (>= 0)
    values: np.ndarray,  # [P]
    S: int,
) -> np.ndarray:
    """[S] median of ``values`` per segment (NaN for segments without samples)."""
    return segment_quantiles(ids, values, S, 0.5)


def select_pixels(
    layers: np.ndarray,  # [L, H, W] int32 segment ids
    valid: np.ndarray,  # [H, W] bool
    depth: Optional[np.ndarray],  # [H, W] z-depth, for outlier rejection
    num_segments: int,
    settings: Optional[LiftSettings] = None,
) -> np.ndarray:  # [L, H, W] int32
    """The pixels each segment is lifted from, as id layers (-1 = not used): the eroded mask
    (or the raw mask when erosion leaves fewer than ``min_points`` valid pixels), restricted
    to valid depth, minus depth outliers."""
    st = settings or LiftSettings()
    S = int(num_segments)
    layers = np.asarray(layers, dtype=np.int32)
    sel = np.where(valid[None], layers, -1)
    if st.erode:
        eroded = erode_layers(layers)
        use_eroded = np.append(_counts(eroded, valid, S) >= st.min_points, False)  # index -1 -> False
        # eroded is a subset of the raw mask: drop a raw pixel only if its segment uses the
        # eroded mask and erosion removed the pixel.
        sel = np.where(use_eroded[sel] & (eroded < 0), -1, sel)
    if depth is not None and st.outlier_mads is not None:
        for l in range(sel.shape[0]):
            pix = sel[l] >= 0
            ids, z = sel[l][pix], depth[pix]
            med = segment_medians(ids, z, S)
            dev = np.abs(z - med[ids])
            mad = segment_medians(ids, dev, S)
            tol = np.maximum(st.outlier_mads * 1.4826 * mad, st.outlier_min_rel * np.abs(med))
            layer = sel[l].copy()
            layer[pix] = np.where(dev > tol[ids], -1, ids)
            sel[l] = layer
    return sel


def _moments(
    layers: np.ndarray,  # [L, H, W] int32, only pixels to use
    points: np.ndarray,  # [H, W, 3] float64, centred
    S: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per segment: count [S], sum of points [S, 3], sum of outer products [S, 3, 3]."""
    count = np.zeros(S)
    first = np.zeros((S, 3))
    second = np.zeros((S, 9))
    for layer in layers:
        pix = layer >= 0
        ids = layer[pix]
        if ids.size == 0:
            continue
        p = points[pix]  # [P, 3]
        outer = (p[:, :, None] * p[:, None, :]).reshape(-1, 9)
        count += np.bincount(ids, minlength=S)[:S]
        for c in range(3):
            first[:, c] += np.bincount(ids, weights=p[:, c], minlength=S)[:S]
        for c in range(9):
            second[:, c] += np.bincount(ids, weights=outer[:, c], minlength=S)[:S]
    return count, first, second.reshape(S, 3, 3)


def segment_scales(
    layers: np.ndarray,  # [L, H, W] int32 segment ids, -1 = none
    points: np.ndarray,  # [H, W, 3] world points at the pixel centres
    valid: np.ndarray,  # [H, W] bool: pixel has a trustworthy depth
    num_segments: int,
    settings: Optional[LiftSettings] = None,
    depth: Optional[np.ndarray] = None,  # [H, W] z-depth for outlier rejection
    footprint: Optional[np.ndarray] = None,  # [H, W] area each pixel covers at its depth ("area")
) -> tuple[np.ndarray, np.ndarray]:
    """Physical scale of every segment from its lifted pixels (see :func:`select_pixels`): the
    largest eigenvalue of their covariance, with ``scale_measure="extent"`` the squared diagonal
    of their robust oriented box (:func:`robust_extent`), with ``"area"`` the sum of their
    ``footprint``. Returns ``(scales [S] float32, NaN for degenerate segments, num_points [S]
    int64)``. A segment with fewer than ``min_points`` usable pixels is degenerate."""
    st = settings or LiftSettings()
    S = int(num_segments)
    if S == 0:
        return np.zeros(0, np.float32), np.zeros(0, np.int64)
    valid = np.asarray(valid, dtype=bool) & np.isfinite(points).all(axis=-1)
    pts = np.asarray(points, dtype=np.float64)
    pts = pts - (pts[valid].mean(axis=0) if valid.any() else 0.0)  # centring keeps E[xx^T] - mu mu^T accurate
    sel = select_pixels(layers, valid, depth, S, st)
    count, first, second = _moments(sel, pts, S)
    ok = count >= max(st.min_points, 2)
    n = np.maximum(count, 1)[:, None]
    mean = first / n
    cov = second / n[..., None] - mean[:, :, None] * mean[:, None, :]
    cov = 0.5 * (cov + cov.transpose(0, 2, 1))
    if st.scale_measure == "extent":
        measure = robust_extent(sel, pts, mean, cov, st.extent_percentile)
    elif st.scale_measure == "area":
        if footprint is None:
            raise ValueError('scale_measure "area" needs the pixels\' footprints')
        fp = np.asarray(footprint, dtype=np.float64)
        measure = np.zeros(S)
        for layer in sel:
            pix = layer >= 0
            measure += np.bincount(layer[pix], weights=fp[pix], minlength=S)[:S]
    else:
        measure = np.linalg.eigvalsh(cov)[:, -1]
    scales = np.where(ok, np.maximum(measure, 0.0), np.nan).astype(np.float32)
    return scales, count.astype(np.int64)


def robust_extent(
    layers: np.ndarray,  # [L, H, W] int32, only pixels to use
    points: np.ndarray,  # [H, W, 3] float64
    mean: np.ndarray,  # [S, 3] per-segment mean of its points
    cov: np.ndarray,  # [S, 3, 3] per-segment covariance
    percentile: float,
) -> np.ndarray:  # [S] float64 (length^2), NaN without points
    """Squared diagonal of each segment's robust oriented box: along each principal axis of
    its points (eigenvectors of ``cov``), the range between the ``percentile`` and
    ``100 - percentile`` percentiles of the points' coordinates; summed squares of the three."""
    S = mean.shape[0]
    axes = np.linalg.eigh(cov)[1]  # [S, 3, 3] columns = principal axes
    ids_all, proj_all = [], []
    for layer in layers:
        pix = layer >= 0
        ids = layer[pix]
        if ids.size:
            proj_all.append(np.einsum("pi,pij->pj", points[pix] - mean[ids], axes[ids]))  # [P, 3]
            ids_all.append(ids)
    if not ids_all:
        return np.full(S, np.nan)
    ids, proj = np.concatenate(ids_all), np.concatenate(proj_all)
    q = percentile / 100.0
    total = np.zeros(S)
    for c in range(3):
        total += (segment_quantiles(ids, proj[:, c], S, 1.0 - q) - segment_quantiles(ids, proj[:, c], S, q)) ** 2
    return total


def lift_view(
    layers: np.ndarray,  # [L, H, W]
    depth: np.ndarray,  # [H, W] z-depth
    valid: np.ndarray,  # [H, W] bool
    camera: Camera,
    num_segments: int,
    settings: Optional[LiftSettings] = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Unproject one view's depth with its camera and measure every segment's scale."""
    depth = np.asarray(depth, dtype=np.float64)
    if depth.shape != (camera.height, camera.width) or layers.shape[1:] != depth.shape:
        raise ValueError(
            f"depth {depth.shape}, segments {layers.shape[1:]} and camera {camera.height}x{camera.width} sizes differ"
        )
    valid = np.asarray(valid, dtype=bool) & np.isfinite(depth) & (depth > 0)
    points = camera.depth_to_points(np.where(valid, depth, 0.0))
    footprint = np.where(valid, depth, 0.0) ** 2 / (camera.fx * camera.fy)  # [H, W] a pixel's area at its depth
    return segment_scales(layers, points, valid, num_segments, settings, depth=depth, footprint=footprint)


# ----------------------------------------------------------------------------- depth sources
def render_depth_provider(gaussians, cameras: list[Camera], min_alpha: float = 0.5, **render_kw) -> DepthProvider:
    """Expected z-depth of fitted Gaussians (``n2f2.render``); pixels with accumulated opacity
    <= ``min_alpha`` have no trustworthy depth."""
    import torch

    from ..render import render_rgb

    def provide(i: int) -> tuple[np.ndarray, np.ndarray]:
        with torch.no_grad():
            out = render_rgb(gaussians, cameras[i], **render_kw)
        depth = out.depth[..., 0].detach().cpu().numpy().astype(np.float64)
        alpha = out.alpha[..., 0].detach().cpu().numpy()
        return depth, alpha > min_alpha

    return provide


def gt_depth_provider(scene) -> DepthProvider:
    """The demo scene's exact depth (``depth/<stem>.npy``), resized to the scene's cameras
    (nearest, at pixel centres); 0 / non-finite depth = background."""
    if scene.ground_truth is None:
        raise InputError(
            scene.root,
            "--depth-source gt needs a scene with exact depth maps (depth/*.npy, as the built-in demo scene has)",
        )
    from .segmenters import resize_nearest

    # Every view's depth is needed: a missing file fails now, not after the first images.
    missing = [i for i in range(len(scene.cameras)) if not scene.ground_truth.depth_path(i).is_file()]
    if missing:
        n = len(missing)
        raise InputError(
            scene.ground_truth.depth_path(missing[0]),
            "missing" + (f" (and {n - 1} other views' depth)" if n > 1 else "") + "; --depth-source gt needs "
            "every view's depth map (--depth-source render lifts with the Gaussians' depth)",
        )

    def provide(i: int) -> tuple[np.ndarray, np.ndarray]:
        gt = scene.ground_truth
        path = gt.root / "depth" / f"{gt.image_names[i]}.npy"
        try:
            depth = np.asarray(gt.depth(i), dtype=np.float64)
        except (OSError, ValueError) as e:
            raise InputError(path, f"cannot read depth ({e})") from None
        cam = scene.cameras[i]
        if depth.ndim != 2:
            raise InputError(path, f"expected a depth map [H, W], got shape {depth.shape}")
        if depth.shape != (cam.height, cam.width):
            depth = resize_nearest(depth[None], cam.height, cam.width)[0]
        valid = np.isfinite(depth) & (depth > 0)
        return depth, valid

    return provide
