"""Per-view node id maps of a decomposition: at every level, each pixel's node is the one whose
Gaussians contribute most to it (the sum of their compositing weights ``alpha_i T_i``), -1 where
no Gaussian contributes; ids are the global node ids, the same in every view.

:func:`node_id_maps` renders each level's visible nodes as indicator channels, a block of
channels at a time, over the Gaussians that touch the view; :func:`node_id_maps_reference`
renders every node of a level at once with the slow reference rasterizer (tests compare them)."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..cameras import Camera

CHANNELS = 32  # indicator channels per pass of the fast path


def _indicators(ids: Tensor, nodes: Tensor) -> Tensor:  # ids [n], nodes [C] -> [n, C] float
    return (ids[:, None] == nodes[None, :]).float()


def _argmax_ids(best: Tensor, best_node: Tensor) -> np.ndarray:  # [H, W] each -> int32 [H, W]
    return torch.where(best > 0, best_node, torch.full_like(best_node, -1)).numpy().astype(np.int32)


@torch.no_grad()
def node_id_maps(
    gaussians,  # n2f2.gaussians.Gaussians (CPU or CUDA)
    gaussian_nodes: np.ndarray,  # [N, L] int node id per Gaussian and level
    camera: Camera,
    channels: int = CHANNELS,
) -> np.ndarray:  # -> int32 [L, H, W], coarsest level first
    from ..render import rasterize

    g = gaussians
    means, quats, scales, opac = g.means.detach(), g.quats.detach(), g.scales.detach(), g.opacities.detach()
    probe = rasterize(means, quats, scales, opac, torch.zeros_like(means[:, :1]), camera)
    seen = (probe.radii > 0).cpu()  # Gaussians that touch the view: the only ones that can contribute
    idx = torch.nonzero(seen).squeeze(1)
    H, W_ = camera.height, camera.width
    out = np.full((gaussian_nodes.shape[1], H, W_), -1, dtype=np.int32)
    if idx.numel() == 0:
        return out
    sel = idx.to(means.device)
    s_means, s_quats, s_scales, s_opac = means[sel], quats[sel], scales[sel], opac[sel]
    for level in range(gaussian_nodes.shape[1]):
        ids = torch.from_numpy(gaussian_nodes[idx.numpy(), level].astype(np.int64))
        visible = torch.unique(ids)
        best = torch.zeros(H, W_)
        best_node = torch.full((H, W_), -1, dtype=torch.long)
        for a in range(0, visible.numel(), channels):
            block = visible[a : a + channels]
            feats = _indicators(ids, block).to(s_means)
            cov = rasterize(s_means, s_quats, s_scales, s_opac, feats, camera).features.cpu()  # [H, W, c]
            value, arg = cov.max(dim=-1)
            better = value > best  # ties keep the earlier (smaller) id
            best = torch.where(better, value, best)
            best_node = torch.where(better, block[arg], best_node)
        out[level] = _argmax_ids(best, best_node)
    return out


@torch.no_grad()
def node_id_maps_reference(
    gaussians,
    gaussian_nodes: np.ndarray,  # [N, L]
    camera: Camera,
) -> np.ndarray:  # -> int32 [L, H, W]
    """Every node of a level in one render of the reference rasterizer, argmax per pixel."""
    from ..render.reference import rasterize_reference

    g = gaussians
    out = []
    for level in range(gaussian_nodes.shape[1]):
        ids = torch.from_numpy(gaussian_nodes[:, level].astype(np.int64))
        nodes = torch.unique(ids)
        feats = _indicators(ids, nodes).to(g.means.dtype)
        cov = rasterize_reference(
            g.means.detach(), g.quats.detach(), g.scales.detach(), g.opacities.detach(), feats, camera
        )
        value, arg = cov.features.max(dim=-1)
        out.append(_argmax_ids(value, nodes[arg]))
    return np.stack(out)


def palette(ids: np.ndarray) -> np.ndarray:  # int [...] -> uint8 [..., 3]
    """:func:`n2f2.data.synthetic.contact_sheet.id_colors` as 8-bit RGB, black for -1."""
    from ..data.synthetic.contact_sheet import id_colors

    return np.round(id_colors(ids) * 255.0).astype(np.uint8)
