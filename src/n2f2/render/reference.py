"""Slow brute-force Gaussian rasterizer: every pixel against every Gaussian, for tests only.

Written independently of the tiled backend (no tiles, no bounding boxes, no log-space
polynomial, plain autograd, explicit 2x2 matrix inverse) so that agreement between the two
is evidence, not tautology. The rules are those of 3DGS:

* ``alpha = min(o * exp(-0.5 d^T Sigma2d^-1 d), alpha_clamp)``; ``alpha < alpha_min`` is skipped;
* Gaussians are blended front to back by camera z;
* the Gaussian that would bring a pixel's transmittance below ``transmittance_min`` is not
  blended and the pixel stops.
"""

from __future__ import annotations

import torch
from torch import Tensor

from n2f2.cameras import Camera


def _rotation(q: Tensor) -> Tensor:  # q [N, 4] wxyz -> [N, 3, 3]
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    rows = [
        [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z],
    ]
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


def rasterize_reference(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] wxyz, any norm
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    features: Tensor,  # [N, C]
    camera: Camera,
    *,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    alpha_clamp: float = 0.99,
    alpha_min: float = 1.0 / 255.0,
    transmittance_min: float = 1e-4,
    background: Tensor | None = None,  # [C]
):
    """Same inputs and output type as :func:`n2f2.render.rasterize` (``radii`` is a 0/1
    visibility flag here: "contributes to at least one pixel")."""
    from n2f2.render import RenderOutput

    dtype, device = means.dtype, means.device
    W = torch.as_tensor(camera.R, dtype=dtype, device=device)
    t = torch.as_tensor(camera.t, dtype=dtype, device=device)
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    H_img, W_img = camera.height, camera.width

    pc = torch.einsum("ij,nj->ni", W, means) + t  # [N, 3]
    z = pc[:, 2]
    in_range = (z > near) & (z < far)
    zs = torch.where(in_range, z, torch.ones_like(z))
    u = fx * pc[:, 0] / zs + cx
    v = fy * pc[:, 1] / zs + cy

    S = torch.diag_embed(scales * scales)
    Rq = _rotation(quats)
    sigma_world = Rq @ S @ Rq.transpose(1, 2)
    sigma_cam = W @ sigma_world @ W.T  # [N, 3, 3]
    # Jacobian at the centre with x/z, y/z clamped to 1.3x the field of view (3DGS).
    limx_pos, limx_neg = (W_img - cx) / fx + 0.15 * W_img / fx, cx / fx + 0.15 * W_img / fx
    limy_pos, limy_neg = (H_img - cy) / fy + 0.15 * H_img / fy, cy / fy + 0.15 * H_img / fy
    xz = torch.clamp(pc[:, 0] / zs, -limx_neg, limx_pos)
    yz = torch.clamp(pc[:, 1] / zs, -limy_neg, limy_pos)
    J = torch.zeros(means.shape[0], 2, 3, dtype=dtype, device=device)
    J[:, 0, 0] = fx / zs
    J[:, 0, 2] = -fx * xz / zs
    J[:, 1, 1] = fy / zs
    J[:, 1, 2] = -fy * yz / zs
    cov2d = J @ sigma_cam @ J.transpose(1, 2) + eps2d * torch.eye(2, dtype=dtype, device=device)
    conic = torch.linalg.inv(cov2d)  # [N, 2, 2]

    jj, ii = torch.meshgrid(
        torch.arange(H_img, dtype=dtype, device=device), torch.arange(W_img, dtype=dtype, device=device), indexing="ij"
    )
    pix = torch.stack([ii + 0.5, jj + 0.5], dim=-1).reshape(-1, 2)  # [P, 2]
    means2d = torch.stack([u, v], -1)  # [N, 2]
    d = pix[:, None, :] - means2d[None]  # [P, N, 2]
    maha = torch.einsum("pni,nij,pnj->pn", d, conic, d)
    alpha = torch.clamp(opacities[None] * torch.exp(-0.5 * maha), max=alpha_clamp)
    alpha = torch.where((alpha >= alpha_min) & in_range[None], alpha, torch.zeros_like(alpha))

    P = pix.shape[0]
    C = features.shape[1]
    T = torch.ones(P, dtype=dtype, device=device)
    done = torch.zeros(P, dtype=torch.bool, device=device)
    img = torch.zeros(P, C, dtype=dtype, device=device)
    dsum = torch.zeros(P, dtype=dtype, device=device)
    contributes = torch.zeros(means.shape[0], dtype=torch.bool, device=device)
    for i in torch.argsort(z.detach(), stable=True).tolist():  # front to back
        a = alpha[:, i]
        nxt = T * (1 - a)
        stop = ~done & (nxt < transmittance_min)
        done = done | stop
        a = torch.where(done, torch.zeros_like(a), a)
        w = a * T
        img = img + w[:, None] * features[i][None]
        dsum = dsum + w * z[i]
        T = T * (1 - a)
        contributes[i] = bool((w > 0).any())
    alpha_img = (1 - T).reshape(H_img, W_img, 1)
    feat = img.reshape(H_img, W_img, C)
    if background is not None:
        feat = feat + background.to(dtype) * (1 - alpha_img)
    dsum = dsum.reshape(H_img, W_img, 1)
    depth = torch.where(alpha_img > 0, dsum / alpha_img.clamp_min(1e-30), torch.zeros_like(dsum))
    return RenderOutput(features=feat, alpha=alpha_img, depth=depth, means2d=means2d, radii=contributes.to(torch.int32))


def random_scene(
    n: int,  # number of Gaussians
    size: int,  # square image side in pixels
    channels: int,  # feature width C
    seed: int = 0,
    *,
    device: torch.device | str = "cpu",
) -> tuple[list[Tensor], Camera]:
    """Random Gaussians in front of a ``size`` x ``size`` camera, for benchmarks and backend
    comparisons: ``[means [N, 3], quats [N, 4], scales [N, 3], opacities [N], features [N, C]]``.

    Centres spread through the view frustum at depths 2..6, random rotations, anisotropic
    scales sized so that each pixel is covered by a few tens of Gaussians (like a trained 3DGS
    scene), opacities uniform in [0.05, 0.95], features uniform in [0, 1]."""
    import math

    import numpy as np

    g = torch.Generator().manual_seed(seed)
    focal = size * 0.9  # ~58 degree field of view
    camera = Camera(focal, focal, size / 2, size / 2, size, size, R=np.eye(3), t=np.zeros(3))
    z = torch.rand(n, generator=g) * 4 + 2
    xy = (torch.rand(n, 2, generator=g) - 0.5) * 1.1 * size / focal * z[:, None]
    means = torch.cat([xy, z[:, None]], 1)
    # Projected standard deviation ~ 1.2 * size / sqrt(n) pixels, times a log-uniform spread.
    sigma_px = 1.2 * size / math.sqrt(n) * torch.exp(torch.randn(n, 3, generator=g) * 0.4)
    scales = sigma_px * z[:, None] / focal
    quats = torch.randn(n, 4, generator=g)
    opacities = torch.rand(n, generator=g) * 0.9 + 0.05
    features = torch.rand(n, channels, generator=g)
    return [t.to(device) for t in (means, quats, scales, opacities, features)], camera
