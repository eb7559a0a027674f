"""The rasterizer's kernels compiled (or loaded from numba's disk cache) by a tiny render: what
the child of :func:`n2f2.render.numba_runtime.compile_in_background` runs first.

A module of its own: it renders through :func:`n2f2.render.rasterize`, and that function's
package imports the kernels' modules."""

from __future__ import annotations

import torch

from n2f2.cameras import Camera
from n2f2.render import eval_sh, rasterize, rasterize_in_bands


def warm_up() -> None:
    """Compile (or load from the cache) every kernel a pipeline uses: a tiny render with
    gradients (the fit) and one without (the trainer's blend weights, queries, evaluation)."""
    gen = torch.Generator().manual_seed(0)
    n = 32
    means = (torch.rand(n, 3, generator=gen) - 0.5) + torch.tensor([0.0, 0.0, 3.0])
    quats, scales, opacities = torch.randn(n, 4, generator=gen), torch.full((n, 3), 0.05), torch.full((n,), 0.5)
    camera = Camera(fx=40.0, fy=40.0, cx=8.0, cy=8.0, width=16, height=16)
    features = torch.rand(n, 4, generator=gen, requires_grad=True)
    out = rasterize(means.requires_grad_(), quats, scales, opacities, features, camera, backend="numba")
    (out.features.sum() + out.depth.sum()).backward()
    sh = torch.randn(n, 16, 3, generator=gen, requires_grad=True)  # the fit's colours (numba_sh)
    eval_sh(sh, means - torch.tensor(camera.center, dtype=torch.float32), 3).sum().backward()
    with torch.no_grad():
        rasterize_in_bands(means.detach(), quats, scales, opacities, features.detach(), camera, backend="numba")
