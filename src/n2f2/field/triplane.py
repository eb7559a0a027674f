"""Backbone encoders of the feature field: the point -> low-dimensional feature part that runs
*before* the MLP (so its output is what deferred rendering rasterizes).

* :class:`TriPlane` (paper Sec. 3.1, K-Planes style): three axis-aligned feature planes
  (xy, xz, yz), bilinearly sampled and summed (or multiplied). Paper default 512^2 x 64.
* :class:`PositionalEncoding` (paper appendix "backbone components", MLP-only backbone):
  NeRF's frequency encoding ``[x, sin(2^k pi x), cos(2^k pi x)]``, k = 0 .. L-1. No parameters.

Both take points already normalised to ``[-1, 1]^3`` (the field does that with the scene's
bounding box).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ..sparse import constant_sparse_matmul, csr_matrix, transpose_csr

# Plane i is spanned by these two coordinate axes (xy, xz, yz).
PLANE_AXES = ((0, 1), (0, 2), (1, 2))


@dataclass
class PlaneTaps:
    """Bilinear taps of fixed points on the three planes (see :meth:`TriPlane.taps`)."""

    index: Tensor  # [3, N * 4] long flat texel index (row * R + col) of each point's 4 corners, per plane
    weight: Tensor  # [3, N, 4] bilinear weights of those corners
    # "sum" reduce: the same taps as one CSR matrix [N, 3 R^2] over channels-last texel rows
    # (plane p's texel t is row p R^2 + t), and its transpose for the backward pass.
    matrix: Optional[Tensor] = None
    matrix_t: Optional[Tensor] = None


class TriPlane(nn.Module):
    """Three ``channels x resolution x resolution`` planes; a point's feature is the sum
    (``reduce="sum"``, nerfstudio's default) or product (``"product"``, K-Planes) of its
    bilinear samples on the three planes.

    Points outside ``[-1, 1]`` read the border texel (``padding_mode="border"``), so a floater
    outside the bounding box gets the feature of the nearest box face instead of zero.

    The parameter is ``texels [3, R, R, C]`` (channels last): the training fast path reads it as
    ``[3 R^2, C]`` rows, a view, and its gradient and Adam's update run on one contiguous tensor
    (on CPU, a channels-first parameter cost a copy of the planes each way per step).
    :attr:`planes` is the usual ``[3, C, R, R]`` view of it. Fields saved with a ``planes``
    parameter (n2f2 before the texel layout) load unchanged.
    """

    def __init__(self, resolution: int = 512, channels: int = 64, reduce: str = "sum", init_scale: float = 0.1) -> None:
        super().__init__()
        if resolution < 2 or channels < 1:
            raise ValueError(f"TriPlane needs resolution >= 2 and channels >= 1, got {resolution}, {channels}")
        if reduce not in ("sum", "product"):
            raise ValueError(f"TriPlane reduce must be 'sum' or 'product', got {reduce!r}")
        self.resolution = int(resolution)
        self.channels = int(channels)
        self.reduce = reduce
        if reduce == "sum":
            # Small random values (nerfstudio TriplaneEncoding): sum of three ~N(0, 0.1^2).
            init = init_scale * torch.randn(3, channels, resolution, resolution)
        else:
            # K-Planes: values near 1 so the product of three planes starts well away from zero.
            init = torch.empty(3, channels, resolution, resolution).uniform_(0.1, 0.5) + 0.5
        self.texels = nn.Parameter(init.permute(0, 2, 3, 1).contiguous())  # [3, R, R, C]

    @property
    def planes(self) -> Tensor:  # [3, C, R, R], a view of the texels
        return self.texels.permute(0, 3, 1, 2)

    def _load_from_state_dict(self, state_dict: dict, prefix: str, *args: Any, **kwargs: Any) -> None:
        planes = state_dict.pop(prefix + "planes", None)  # saved before the texel layout: [3, C, R, R]
        if planes is not None and prefix + "texels" not in state_dict:
            state_dict[prefix + "texels"] = planes.permute(0, 2, 3, 1)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @property
    def out_dim(self) -> int:
        return self.channels

    def forward(self, xyz: Tensor) -> Tensor:  # xyz [N, 3] in [-1, 1] -> [N, C]
        # grid_sample reads grid[..., 0] as the column (width) and grid[..., 1] as the row.
        coords = torch.stack([xyz[:, list(a)] for a in PLANE_AXES], dim=0)  # [3, N, 2]
        samples = F.grid_sample(
            self.planes,
            coords.unsqueeze(2).to(self.planes.dtype),
            mode="bilinear",
            padding_mode="border",
            align_corners=True,
        )  # [3, C, N, 1]
        samples = samples.squeeze(-1)  # [3, C, N]
        out = samples.sum(0) if self.reduce == "sum" else samples.prod(0)  # [C, N]
        return out.t()  # [N, C]

    # Fast path for points that do not move while the planes train (the frozen Gaussian
    # centres): the bilinear corners and weights are computed once. With "sum", a step is one
    # product with a constant sparse matrix (backward: its transpose, no scatter); with
    # "product", a gather of texel columns per plane. Same values and gradients as ``forward``
    # (grid_sample's backward scatters channel by channel and costs ~3x more on CPU).
    @torch.no_grad()
    def taps(self, xyz: Tensor) -> PlaneTaps:  # xyz [N, 3] in [-1, 1]
        """Corners and weights of ``xyz`` on each plane, as grid_sample computes them
        (``align_corners=True``, border padding: coordinates are clamped into the plane)."""
        R = self.resolution
        coords = torch.stack([xyz[:, list(a)] for a in PLANE_AXES], dim=0).to(self.planes.dtype)  # [3, N, 2]
        pix = ((coords + 1.0) * (0.5 * (R - 1))).clamp_(0.0, R - 1.0)  # (col, row) texel coordinates
        lo = pix.floor().clamp_(max=R - 2.0)  # a point on the last texel uses the last cell, weight 1
        frac = pix - lo  # [3, N, 2]
        col, row = lo.long().unbind(-1)
        fc, fr = frac.unbind(-1)
        top = row * R + col
        index = torch.stack([top, top + 1, top + R, top + R + 1], dim=-1)  # [3, N, 4]
        weight = torch.stack([(1 - fc) * (1 - fr), fc * (1 - fr), (1 - fc) * fr, fc * fr], dim=-1)
        taps = PlaneTaps(index.reshape(3, -1).contiguous(), weight.contiguous())
        if self.reduce == "sum":
            n = xyz.shape[0]
            plane_offset = torch.arange(3, device=index.device)[:, None, None] * (R * R)
            cols = (index + plane_offset).permute(1, 0, 2).reshape(-1)  # [N * 12], ascending per row
            crow = torch.arange(n + 1, device=index.device) * 12
            taps.matrix = csr_matrix(crow, cols, weight.permute(1, 0, 2).reshape(-1), (n, 3 * R * R))
            taps.matrix_t = transpose_csr(taps.matrix)
        return taps

    def sample(self, taps: PlaneTaps) -> Tensor:  # -> [N, C], equal to forward(xyz) of the taps' points
        C, R = self.channels, self.resolution
        if taps.matrix is not None:
            texels = self.texels.view(3 * R * R, C)  # channels-last rows
            return constant_sparse_matmul(taps.matrix, texels, taps.matrix_t)
        n = taps.weight.shape[1]
        out = None
        for p in range(3):
            corners = self.texels[p].view(R * R, C).index_select(0, taps.index[p]).view(n, 4, C)
            value = (corners * taps.weight[p].unsqueeze(-1)).sum(1)  # [N, C]
            out = value if out is None else (out + value if self.reduce == "sum" else out * value)
        assert out is not None  # the loop over the three planes ran
        return out

    def extra_repr(self) -> str:
        return f"resolution={self.resolution}, channels={self.channels}, reduce={self.reduce}"


class PositionalEncoding(nn.Module):
    """``[x, sin(2^0 pi x), cos(2^0 pi x), ..., sin(2^(L-1) pi x), cos(2^(L-1) pi x)]`` per
    coordinate; output dim ``3 + 6 L``."""

    def __init__(self, num_frequencies: int = 8) -> None:
        super().__init__()
        if num_frequencies < 0:
            raise ValueError(f"number of PE frequencies must be >= 0, got {num_frequencies}")
        self.num_frequencies = int(num_frequencies)
        self.freqs: Tensor  # [L] registered buffer
        self.register_buffer(
            "freqs", math.pi * 2.0 ** torch.arange(num_frequencies, dtype=torch.float32), persistent=False
        )

    @property
    def out_dim(self) -> int:
        return 3 + 6 * self.num_frequencies

    def forward(self, xyz: Tensor) -> Tensor:  # xyz [N, 3] in [-1, 1] -> [N, 3 + 6L]
        angles = (xyz.unsqueeze(-1) * self.freqs.to(xyz.dtype)).flatten(1)  # [N, 3L]
        return torch.cat([xyz, torch.sin(angles), torch.cos(angles)], dim=-1)

    def extra_repr(self) -> str:
        return f"num_frequencies={self.num_frequencies}"
