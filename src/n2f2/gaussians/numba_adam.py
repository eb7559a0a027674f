"""The fit's Adam update compiled with numba: :class:`n2f2.gaussians.optim.GaussianAdam`'s torch
update (the reference), one pass over each parameter instead of ten.

The torch update walks a parameter, its gradient and both moments in about ten elementwise
operations (two for each moment, three for the denominator, the division, the rate, the
subtraction), each a pass over memory and an allocation; at the demo fit's 12k Gaussians x 59
values that is ~3 ms of a ~40 ms step. Here each value's moments and step are computed in
registers, in float32 with torch's operation order, and written once: the same update up to
float rounding (tests compare both against ``torch.optim.Adam``).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from n2f2.render.numba_runtime import KERNEL_LOCK, numba_threads

try:  # optional at import time, as in the rasterizer's kernels
    import numba
    from numba import njit, prange
except ImportError:  # pragma: no cover - numba is a declared dependency
    numba = None

if numba is not None:

    @njit(cache=True, nogil=True, parallel=True)
    def _update(p, g, m, v, rate, b1, c1, b2, c2, sqrt_bc2, eps, nthreads):
        """Adam on rows [N, R], float32 throughout: ``c1 = 1 - b1`` and ``c2 = 1 - b2`` (each
        rounded from float64, as torch rounds its scalars), ``rate`` [R] is lr / (1 - b1^t)."""
        n, r = p.shape
        for thread in prange(nthreads):
            for i in range(thread * n // nthreads, (thread + 1) * n // nthreads):
                for j in range(r):
                    gj = g[i, j]
                    mj = m[i, j] * b1 + gj * c1
                    vj = v[i, j] * b2 + gj * gj * c2
                    m[i, j] = mj
                    v[i, j] = vj
                    p[i, j] -= mj / (np.sqrt(vj) / sqrt_bc2 + eps) * rate[j]


def usable(params: list[Tensor]) -> bool:
    """Whether the compiled update takes these parameters: contiguous CPU float32, numba present."""
    return numba is not None and all(
        t.device.type == "cpu" and t.dtype == torch.float32 and t.is_contiguous() for t in params
    )


@torch.no_grad()
def adam_update(
    p: Tensor,  # [N, ...] parameter, updated in place
    g: Tensor,  # like p, its gradient
    m: Tensor,  # like p, first moment, updated in place
    v: Tensor,  # like p, second moment, updated in place
    lr: float | Tensor,  # a number, or a tensor broadcastable to p[0] (per column of a row)
    betas: tuple[float, float],
    step: int,  # t, counted from 1
    eps: float,
) -> None:
    """One Adam step of ``p`` (no weight decay), as ``torch.optim.Adam``:
    ``p -= lr / (1 - b1^t) * m / (sqrt(v) / sqrt(1 - b2^t) + eps)``."""
    if p.numel() == 0:
        return
    b1, b2 = betas
    n = p.shape[0] if p.dim() else 1
    p_rows, g_rows, m_rows, v_rows = (t.detach().reshape(n, -1).numpy() for t in (p, g.contiguous(), m, v))
    r = p_rows.shape[1]
    bc1, bc2 = 1.0 - b1**step, 1.0 - b2**step
    if isinstance(lr, Tensor):
        if lr.dim() == p.dim() and lr.shape[0] != 1:
            raise ValueError(f"a rate per row ({tuple(lr.shape)}) is not a rate per column of {tuple(p.shape)}")
        per_column = lr.detach().to(torch.float32).expand(p.shape)[0] if p.dim() else lr.detach().float()
        rate = (per_column / bc1).reshape(r).contiguous().numpy()
    else:
        rate = np.full(r, lr / bc1, dtype=np.float32)
    f32 = np.float32
    with KERNEL_LOCK:
        _update(
            p_rows,
            g_rows,
            m_rows,
            v_rows,
            rate,
            f32(b1),
            f32(1 - b1),
            f32(b2),
            f32(1 - b2),
            f32(np.sqrt(bc2)),
            f32(eps),
            numba_threads(),
        )


def warm_up() -> None:
    """Compile (or load from the cache) the update with the argument types a fit step passes
    (:func:`n2f2.render.numba_runtime.compile_in_background` runs this)."""
    if numba is not None:
        p, g = torch.zeros(2, 3), torch.ones(2, 3)
        adam_update(p, g, torch.zeros(2, 3), torch.zeros(2, 3), 0.1, (0.9, 0.999), 1, 1e-15)
