"""What the 3D viewer sends for its splats: the Gaussians as viser's arrays (centres,
covariances, colours, opacities), and the per-Gaussian colours of its displays (turbo heatmap of the
relevancy, the protocol's selection, dimming), packed as the RGBA words of viser's splat buffer."""

from __future__ import annotations

from typing import Any, Optional

import numpy as np

DIM_COLOR = 0.25  # colour factor of unselected Gaussians in the "selection" display
DIM_OPACITY = 0.15  # opacity factor of unselected Gaussians
SELECTION_THRESHOLD = 0.4  # the evaluation protocol's mask threshold (LangSplat --mask_thresh)


# ----------------------------------------------------------------------------- splat arrays
def splat_covariances(
    scales: np.ndarray,  # [N, 3] standard deviations along the local axes
    quats: np.ndarray,  # [N, 4] wxyz, any norm
) -> np.ndarray:  # [N, 3, 3] float32 world-space covariances
    """``R diag(s^2) R^T`` per Gaussian, ``R`` the rotation of the normalised quaternion."""
    import torch

    from ..gaussians.model import quat_to_rotmat

    s = torch.as_tensor(np.asarray(scales, dtype=np.float32))
    R = quat_to_rotmat(torch.as_tensor(np.asarray(quats, dtype=np.float32)))  # [N, 3, 3]
    return ((R * (s * s)[:, None, :]) @ R.transpose(1, 2)).numpy()


def splat_colors(
    dc: np.ndarray,  # [N, 3] degree-0 SH coefficients
) -> np.ndarray:  # [N, 3] float32 in [0, 1]
    """The colour a Gaussian shows from every direction: ``SH_C0 * dc + 0.5``, clipped."""
    import torch

    from ..gaussians.model import sh_to_rgb

    return sh_to_rgb(torch.as_tensor(np.asarray(dc, dtype=np.float32))).clamp(0.0, 1.0).numpy()


def splat_arrays(gaussians: Any) -> dict[str, np.ndarray]:
    """What ``viser``'s ``add_gaussian_splats`` takes, from a :class:`n2f2.gaussians.Gaussians`:
    ``centers [N, 3]``, ``covariances [N, 3, 3]``, ``rgbs [N, 3]``, ``opacities [N, 1]``."""
    import torch

    with torch.no_grad():
        g = gaussians
        return {
            "centers": g.means.detach().float().cpu().numpy(),
            "covariances": splat_covariances(g.scales.detach().cpu().numpy(), g.quats.detach().cpu().numpy()),
            "rgbs": splat_colors(g.sh[:, 0].detach().cpu().numpy()),
            "opacities": g.opacities.detach().float().cpu().numpy()[:, None],
        }


# ----------------------------------------------------------------------------- colours
_TURBO: Optional[np.ndarray] = None


def turbo_lut() -> np.ndarray:  # [256, 3] uint8
    """matplotlib's turbo colour map: its 256 entries, as 8-bit colours."""
    global _TURBO
    if _TURBO is None:
        from matplotlib import colormaps

        cmap = colormaps["turbo"]
        _TURBO = (cmap(np.arange(cmap.N))[:, :3] * 255.0 + 0.5).astype(np.uint8)
    return _TURBO


def normalized_relevancy(
    relevancy: np.ndarray,  # [Q, N]
) -> np.ndarray:  # [N] float32 in [0, 1]
    """Per query min-max normalised relevancy, maximum over queries. A flat query
    (:func:`n2f2.query.maps.is_flat`) gives its mean relevancy on the absolute 0..1 scale, as the
    2D heatmaps draw it, not min-max stretched noise."""
    from ..query.maps import is_flat

    rel = np.asarray(relevancy, dtype=np.float32)
    out = np.zeros(rel.shape[1], np.float32)
    for r in rel:
        lo, hi = float(r.min()), float(r.max())
        if is_flat(r):
            np.maximum(out, np.float32(np.clip(r.mean(dtype=np.float64), 0.0, 1.0)), out=out)
        elif hi > lo:
            np.maximum(out, (r - np.float32(lo)) * np.float32(1.0 / (hi - lo)), out=out)
    return out


def heat_index(
    relevancy: np.ndarray,  # [Q, N]
) -> np.ndarray:  # [N] int32 in [0, 256)
    """Turbo entry of :func:`normalized_relevancy`: ``floor(256 v)``, as matplotlib picks it."""
    v = normalized_relevancy(relevancy)
    v *= np.float32(256.0)
    return np.minimum(v.astype(np.int32), 255)


def heat_colors(
    relevancy: np.ndarray,  # [Q, N]
) -> np.ndarray:  # [N, 3] uint8
    """Turbo colours of :func:`normalized_relevancy`."""
    return turbo_lut()[heat_index(relevancy)]


def rgba_words(
    rgba: np.ndarray,  # [N, 4] uint8
) -> np.ndarray:  # [N] uint32
    """RGBA bytes as the one 32-bit word per Gaussian that viser's splat buffer holds (word 7)."""
    return np.ascontiguousarray(rgba, dtype=np.uint8).view(np.uint32)[:, 0]


def selection_scores(
    relevancy: np.ndarray,  # [Q, N]
) -> np.ndarray:  # [N] float32 in [0, 1]
    """Per Gaussian, the largest over queries of the protocol's normalised relevancy
    (:func:`n2f2.eval.protocol.normalized_for_threshold`): selected = score > threshold."""
    from ..query.maps import normalized_for_threshold

    rel = np.asarray(relevancy, dtype=np.float32)
    out = np.zeros(rel.shape[1], np.float32)  # the protocol's values are >= 0
    for r in rel:
        np.maximum(out, normalized_for_threshold(r), out=out)
    return out


def selection_mask(
    relevancy: np.ndarray,  # [Q, N]
    threshold: float = SELECTION_THRESHOLD,
) -> np.ndarray:  # [N] bool
    """Gaussians selected by any query under the protocol's rule on normalised relevancy
    (``normalized_for_threshold(r) > threshold``)."""
    return selection_scores(relevancy) > threshold


_DIM = (np.arange(256) * DIM_COLOR).astype(np.uint8), (np.arange(256) * DIM_OPACITY).astype(np.uint8)


def dimmed(
    rgba: np.ndarray,  # [N, 4] uint8
    keep: np.ndarray,  # [N] bool
) -> np.ndarray:  # [N, 4] uint8
    """Unselected Gaussians darker (x DIM_COLOR) and more transparent (x DIM_OPACITY)."""
    low = np.empty_like(rgba)
    low[:, :3] = _DIM[0][rgba[:, :3]]
    low[:, 3] = _DIM[1][rgba[:, 3]]
    return np.where(keep[:, None], rgba, low)
