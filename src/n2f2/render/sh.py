"""Real spherical harmonics for view-dependent colour, degrees 0..3 (3DGS constants and sign
convention, so checkpoints of the reference implementation render the same colours)."""

from __future__ import annotations

import torch
from torch import Tensor

from n2f2.render.sh_constants import SH_C0, SH_C1, SH_C2, SH_C3


def num_sh_bases(degree: int) -> int:
    """K = (degree + 1)^2 coefficients per colour channel."""
    return (degree + 1) ** 2


def sh_basis(dirs: Tensor, degree: int) -> Tensor:  # dirs [N, 3] unit -> [N, K]
    """The 3DGS SH basis functions evaluated at unit directions."""
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            SH_C2[0] * x * y,
            SH_C2[1] * y * z,
            SH_C2[2] * (2 * zz - xx - yy),
            SH_C2[3] * x * z,
            SH_C2[4] * (xx - yy),
        ]
        if degree >= 3:
            out += [
                SH_C3[0] * y * (3 * xx - yy),
                SH_C3[1] * x * y * z,
                SH_C3[2] * y * (4 * zz - xx - yy),
                SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
                SH_C3[4] * x * (4 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy),
                SH_C3[6] * x * (xx - 3 * yy),
            ]
    return torch.stack(out, dim=-1)


def eval_sh(
    sh: Tensor,  # [N, K, 3] coefficients, K >= (degree + 1)^2 (extra bands are ignored)
    dirs: Tensor,  # [N, 3] viewing directions (camera centre -> Gaussian), any length
    degree: int,
) -> Tensor:  # [N, 3]
    """RGB colour = max(SH(dirs) + 0.5, 0), as 3DGS: compiled on CPU
    (:mod:`n2f2.render.numba_sh`), else :func:`eval_sh_torch`."""
    k = num_sh_bases(degree)
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    if sh.shape[-2] < k:
        raise ValueError(f"SH degree {degree} needs {k} coefficients per channel, got {sh.shape[-2]}")
    from . import numba_sh  # here: numba loads with the first colours, not with n2f2.render

    if numba_sh.usable(sh, dirs):
        return numba_sh.sh_colors(sh[:, :k], dirs)
    return eval_sh_torch(sh, dirs, degree)


def eval_sh_torch(
    sh: Tensor,  # [N, K, 3] coefficients, K >= (degree + 1)^2 (extra bands are ignored)
    dirs: Tensor,  # [N, 3] viewing directions (camera centre -> Gaussian), any length
    degree: int,
) -> Tensor:  # [N, 3]
    """:func:`eval_sh` in PyTorch operations (any device; the reference of the compiled path)."""
    k = num_sh_bases(degree)
    if sh.shape[-2] < k:
        raise ValueError(f"SH degree {degree} needs {k} coefficients per channel, got {sh.shape[-2]}")
    d = dirs / torch.linalg.vector_norm(dirs, dim=-1, keepdim=True).clamp_min(1e-12)
    basis = sh_basis(d, degree)  # [N, k]
    return torch.clamp_min(torch.einsum("nk,nkc->nc", basis, sh[:, :k]) + 0.5, 0.0)
