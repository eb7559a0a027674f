"""EWA projection compiled with numba: :func:`n2f2.render.torch_backend.project_gaussians`, one
loop over the Gaussians forward and one backward.

The PyTorch projection is some sixty operations on ``[N]`` and ``[3, 3, N]`` tensors, and its
autograd graph as many again backward: at the ten to twenty thousand Gaussians of a CPU fit
their fixed cost per operation, not the arithmetic, is the time. The compiled pair computes each
Gaussian's camera-space centre, rotation, 2D covariance and conic in registers, and the backward
chains the gradients of the projected centres, conics and depths back to the centres,
quaternions and scales by hand (gsplat's ``fully_fused_projection`` backward follows the same
steps). The torch function stays the reference: same outputs and gradients up to float rounding
(tests compare both), the same validity and the same Jacobian clamp.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from n2f2.render.numba_runtime import FASTMATH, KERNEL_LOCK, numba_threads
from n2f2.render.torch_backend import Projection, project_gaussians

try:  # optional at import time, as in the compositing kernels
    import numba
    from numba import njit, prange
except ImportError:  # pragma: no cover - numba is a declared dependency
    numba = None

if numba is not None:

    @njit(cache=True, nogil=True)
    def _rotation(qw, qx, qy, qz, rot):  # unit quaternion (w, x, y, z) -> rot [3, 3]
        rot[0, 0] = 1 - 2 * (qy * qy + qz * qz)
        rot[0, 1] = 2 * (qx * qy - qw * qz)
        rot[0, 2] = 2 * (qx * qz + qw * qy)
        rot[1, 0] = 2 * (qx * qy + qw * qz)
        rot[1, 1] = 1 - 2 * (qx * qx + qz * qz)
        rot[1, 2] = 2 * (qy * qz - qw * qx)
        rot[2, 0] = 2 * (qx * qz - qw * qy)
        rot[2, 1] = 2 * (qy * qz + qw * qx)
        rot[2, 2] = 1 - 2 * (qx * qx + qy * qy)

    @njit(fastmath=FASTMATH, cache=True, nogil=True)
    def _to_camera(cam, mx, my, mz):  # world point -> camera space (cam [4, 4] world-to-camera)
        x = cam[0, 0] * mx + cam[0, 1] * my + cam[0, 2] * mz + cam[0, 3]
        y = cam[1, 0] * mx + cam[1, 1] * my + cam[1, 2] * mz + cam[1, 3]
        z = cam[2, 0] * mx + cam[2, 1] * my + cam[2, 2] * mz + cam[2, 3]
        return x, y, z

    @njit(parallel=True, fastmath=FASTMATH, cache=True, nogil=True)
    def _forward_kernel(
        means,  # [N, 3]
        quats,  # [N, 4] wxyz, any length
        scales,  # [N, 3]
        opacities,  # [N]
        cam,  # [4, 4] world-to-camera
        intr,  # fx, fy, cx, cy, lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos, near, far, eps2d, alpha_min
        means2d,  # out [N, 2]
        conics,  # out [3, N]
        depths,  # out [N]
        half_extent,  # out [2, N]
        valid,  # out [N] bool
        nthreads,
    ):
        fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
        lxn, lxp, lyn, lyp = intr[4], intr[5], intr[6], intr[7]
        near, far, eps2d, alpha_min = intr[8], intr[9], intr[10], intr[11]
        N = means.shape[0]
        for thread in prange(nthreads):
            rot = np.empty((3, 3))
            for n in range(thread * N // nthreads, (thread + 1) * N // nthreads):
                x, y, z = _to_camera(cam, means[n, 0], means[n, 1], means[n, 2])
                depths[n] = z
                ok = near < z < far
                iz = 1.0 / z if ok else 1.0  # culled entries stay finite, as in the reference
                qw, qx, qy, qz = quats[n, 0], quats[n, 1], quats[n, 2], quats[n, 3]
                r = 1.0 / math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
                _rotation(qw * r, qx * r, qy * r, qz * r, rot)
                txz = min(max(x * iz, -lxn), lxp)
                tyz = min(max(y * iz, -lyn), lyp)
                ca = eps2d
                cb = 0.0
                cc = eps2d
                for j in range(3):  # column j of W R_q diag(s), then of T = J W R_q diag(s)
                    m0 = (cam[0, 0] * rot[0, j] + cam[0, 1] * rot[1, j] + cam[0, 2] * rot[2, j]) * scales[n, j]
                    m1 = (cam[1, 0] * rot[0, j] + cam[1, 1] * rot[1, j] + cam[1, 2] * rot[2, j]) * scales[n, j]
                    m2 = (cam[2, 0] * rot[0, j] + cam[2, 1] * rot[1, j] + cam[2, 2] * rot[2, j]) * scales[n, j]
                    t0 = (m0 - m2 * txz) * (fx * iz)
                    t1 = (m1 - m2 * tyz) * (fy * iz)
                    ca += t0 * t0
                    cb += t0 * t1
                    cc += t1 * t1
                det = ca * cc - cb * cb
                ok = ok and det > 0
                inv_det = 1.0 / det if ok else 1.0
                conics[0, n] = cc * inv_det
                conics[1, n] = -cb * inv_det
                conics[2, n] = ca * inv_det
                u = fx * x * iz + cx
                v = fy * y * iz + cy
                means2d[n, 0] = u
                means2d[n, 1] = v
                level = 2.0 * math.log(max(opacities[n], 1e-30) / alpha_min)
                valid[n] = ok and level > 0 and math.isfinite(u) and math.isfinite(v)
                level = max(level, 0.0)
                half_extent[0, n] = math.sqrt(level * ca)
                half_extent[1, n] = math.sqrt(level * cc)

    @njit(parallel=True, fastmath=FASTMATH, cache=True, nogil=True)
    def _backward_kernel(
        means,
        quats,
        scales,
        cam,
        intr,
        g_means2d,  # [N, 2]
        g_conics,  # [3, N]
        g_depths,  # [N]
        g_means,  # out [N, 3]
        g_quats,  # out [N, 4]
        g_scales,  # out [N, 3]
        nthreads,
    ):
        fx, fy = intr[0], intr[1]
        lxn, lxp, lyn, lyp = intr[4], intr[5], intr[6], intr[7]
        near, far, eps2d = intr[8], intr[9], intr[10]
        N = means.shape[0]
        for thread in prange(nthreads):
            rot = np.empty((3, 3))
            M = np.empty((3, 3))  # W R_q diag(s)
            WR = np.empty((3, 3))  # W R_q
            t0 = np.empty(3)
            t1 = np.empty(3)
            g_rot = np.empty((3, 3))
            for n in range(thread * N // nthreads, (thread + 1) * N // nthreads):
                x, y, z = _to_camera(cam, means[n, 0], means[n, 1], means[n, 2])
                in_range = near < z < far
                iz = 1.0 / z if in_range else 1.0
                qw, qx, qy, qz = quats[n, 0], quats[n, 1], quats[n, 2], quats[n, 3]
                qnorm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
                r = 1.0 / qnorm
                w, a, b, c = qw * r, qx * r, qy * r, qz * r
                _rotation(w, a, b, c, rot)
                xz, yz = x * iz, y * iz
                txz = min(max(xz, -lxn), lxp)
                tyz = min(max(yz, -lyn), lyp)
                ca = eps2d
                cb = 0.0
                cc = eps2d
                for j in range(3):
                    for i in range(3):
                        WR[i, j] = cam[i, 0] * rot[0, j] + cam[i, 1] * rot[1, j] + cam[i, 2] * rot[2, j]
                        M[i, j] = WR[i, j] * scales[n, j]
                    t0[j] = (M[0, j] - M[2, j] * txz) * (fx * iz)
                    t1[j] = (M[1, j] - M[2, j] * tyz) * (fy * iz)
                    ca += t0[j] * t0[j]
                    cb += t0[j] * t1[j]
                    cc += t1[j] * t1[j]
                det = ca * cc - cb * cb
                ok = in_range and det > 0
                inv_det = 1.0 / det if ok else 1.0

                # conics = (cc, -cb, ca) / det; det = ca cc - cb^2 (only where it was used).
                g0, g1, g2 = g_conics[0, n], g_conics[1, n], g_conics[2, n]
                g_cc = g0 * inv_det
                g_cb = -g1 * inv_det
                g_ca = g2 * inv_det
                if ok:
                    g_det = -(g0 * cc - g1 * cb + g2 * ca) * inv_det * inv_det
                    g_ca += g_det * cc
                    g_cc += g_det * ca
                    g_cb -= 2.0 * cb * g_det
                # means2d = (fx x iz + cx, fy y iz + cy); depth = z.
                gu, gv = g_means2d[n, 0], g_means2d[n, 1]
                g_x = gu * fx * iz
                g_y = gv * fy * iz
                g_iz = gu * fx * x + gv * fy * y
                g_z = g_depths[n]
                g_txz = 0.0
                g_tyz = 0.0
                for i in range(3):
                    for j in range(3):
                        g_rot[i, j] = 0.0
                for j in range(3):
                    g_t0 = 2.0 * t0[j] * g_ca + t1[j] * g_cb
                    g_t1 = 2.0 * t1[j] * g_cc + t0[j] * g_cb
                    f0 = fx * iz
                    f1 = fy * iz
                    g_m0 = g_t0 * f0
                    g_m1 = g_t1 * f1
                    g_m2 = -g_t0 * txz * f0 - g_t1 * tyz * f1
                    g_txz -= g_t0 * M[2, j] * f0
                    g_tyz -= g_t1 * M[2, j] * f1
                    g_iz += g_t0 * (M[0, j] - M[2, j] * txz) * fx + g_t1 * (M[1, j] - M[2, j] * tyz) * fy
                    s = scales[n, j]
                    g_scales[n, j] = g_m0 * WR[0, j] + g_m1 * WR[1, j] + g_m2 * WR[2, j]
                    for k in range(3):  # WR = W rot: d/d rot[k, j] = sum_i W[i, k] g_WR[i, j]
                        g_rot[k, j] = (cam[0, k] * g_m0 + cam[1, k] * g_m1 + cam[2, k] * g_m2) * s
                # The clamps pass the gradient inside their range (bounds included), as torch.clamp.
                if -lxn <= xz <= lxp:
                    g_x += g_txz * iz
                    g_iz += g_txz * x
                if -lyn <= yz <= lyp:
                    g_y += g_tyz * iz
                    g_iz += g_tyz * y
                if in_range:
                    g_z -= g_iz * iz * iz
                for k in range(3):  # pc = W m + t
                    g_means[n, k] = cam[0, k] * g_x + cam[1, k] * g_y + cam[2, k] * g_z
                # rot of the unit quaternion (w, a, b, c), then the normalisation.
                gw = 2 * (
                    -c * g_rot[0, 1]
                    + b * g_rot[0, 2]
                    + c * g_rot[1, 0]
                    - a * g_rot[1, 2]
                    - b * g_rot[2, 0]
                    + a * g_rot[2, 1]
                )
                ga = 2 * (
                    b * g_rot[0, 1]
                    + c * g_rot[0, 2]
                    + b * g_rot[1, 0]
                    - 2 * a * g_rot[1, 1]
                    - w * g_rot[1, 2]
                    + c * g_rot[2, 0]
                    + w * g_rot[2, 1]
                    - 2 * a * g_rot[2, 2]
                )
                gb = 2 * (
                    -2 * b * g_rot[0, 0]
                    + a * g_rot[0, 1]
                    + w * g_rot[0, 2]
                    + a * g_rot[1, 0]
                    + c * g_rot[1, 2]
                    - w * g_rot[2, 0]
                    + c * g_rot[2, 1]
                    - 2 * b * g_rot[2, 2]
                )
                gc = 2 * (
                    -2 * c * g_rot[0, 0]
                    - w * g_rot[0, 1]
                    + a * g_rot[0, 2]
                    + w * g_rot[1, 0]
                    - 2 * c * g_rot[1, 1]
                    + b * g_rot[1, 2]
                    + a * g_rot[2, 0]
                    + b * g_rot[2, 1]
                )
                dot = w * gw + a * ga + b * gb + c * gc
                g_quats[n, 0] = (gw - w * dot) * r
                g_quats[n, 1] = (ga - a * dot) * r
                g_quats[n, 2] = (gb - b * dot) * r
                g_quats[n, 3] = (gc - c * dot) * r


def _camera_terms(viewmat: Tensor, K: Tensor, width: int, height: int, near, far, eps2d, alpha_min):
    cam = viewmat.detach().to(torch.float64).contiguous().numpy()
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    intr = np.array(
        [
            fx,
            fy,
            cx,
            cy,
            cx / fx + 0.15 * width / fx,
            (width - cx) / fx + 0.15 * width / fx,
            cy / fy + 0.15 * height / fy,
            (height - cy) / fy + 0.15 * height / fy,
            near,
            far,
            eps2d,
            alpha_min,
        ]
    )
    return cam, intr


class _NumbaProjection(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, cam, intr):
        N = means.shape[0]
        dtype = means.dtype
        arrays = [t.detach().contiguous().numpy() for t in (means, quats, scales, opacities)]
        np_dtype = arrays[0].dtype
        means2d = np.empty((N, 2), np_dtype)
        conics = np.empty((3, N), np_dtype)
        depths = np.empty(N, np_dtype)
        half_extent = np.empty((2, N), np_dtype)
        valid = np.empty(N, np.bool_)
        with KERNEL_LOCK:
            _forward_kernel(
                arrays[0],
                arrays[1],
                arrays[2],
                arrays[3],
                cam,
                intr,
                means2d,
                conics,
                depths,
                half_extent,
                valid,
                numba_threads(),
            )
        ctx.saved = (arrays[:3], cam, intr, dtype)
        out_he, out_valid = torch.from_numpy(half_extent), torch.from_numpy(valid)
        ctx.mark_non_differentiable(out_he, out_valid)
        return torch.from_numpy(means2d), torch.from_numpy(conics), torch.from_numpy(depths), out_he, out_valid

    @staticmethod
    def backward(ctx, g_means2d, g_conics, g_depths, _g_he, _g_valid):
        (means, quats, scales), cam, intr, dtype = ctx.saved
        N = means.shape[0]

        def arr(g, shape):
            return np.zeros(shape, means.dtype) if g is None else g.detach().to(dtype).contiguous().numpy()

        g_means = np.empty_like(means)
        g_quats = np.empty_like(quats)
        g_scales = np.empty_like(scales)
        with KERNEL_LOCK:
            _backward_kernel(
                means,
                quats,
                scales,
                cam,
                intr,
                arr(g_means2d, (N, 2)),
                arr(g_conics, (3, N)),
                arr(g_depths, (N,)),
                g_means,
                g_quats,
                g_scales,
                numba_threads(),
            )
        return torch.from_numpy(g_means), torch.from_numpy(g_quats), torch.from_numpy(g_scales), None, None, None


def usable(means: Tensor) -> bool:
    """Whether the compiled projection takes these inputs: CPU float tensors, numba present."""
    return numba is not None and means.device.type == "cpu" and means.dtype in (torch.float32, torch.float64)


def project_gaussians_numba(
    means: Tensor,  # [N, 3] world-space centres
    quats: Tensor,  # [N, 4] wxyz rotations (normalised here)
    scales: Tensor,  # [N, 3] standard deviations along the local axes (not log)
    opacities: Tensor,  # [N] in (0, 1)
    viewmat: Tensor,  # [4, 4] world-to-camera (OpenCV axes)
    K: Tensor,  # [3, 3] intrinsics
    width: int,
    height: int,
    *,
    near: float = 0.01,
    far: float = 1e10,
    eps2d: float = 0.3,
    alpha_min: float = 1.0 / 255.0,
) -> Projection:
    """:func:`~n2f2.render.torch_backend.project_gaussians`, compiled (CPU; differentiable in the
    centres, quaternions and scales, as the reference)."""
    if not usable(means):
        return project_gaussians(
            means,
            quats,
            scales,
            opacities,
            viewmat,
            K,
            width,
            height,
            near=near,
            far=far,
            eps2d=eps2d,
            alpha_min=alpha_min,
        )
    cam, intr = _camera_terms(viewmat, K, width, height, near, far, eps2d, alpha_min)
    dtype = means.dtype
    m2d, conics, depths, he, valid = _NumbaProjection.apply(
        means, quats.to(dtype), scales.to(dtype), opacities.detach().to(dtype), cam, intr
    )
    return Projection(m2d, conics, depths, he, valid)
