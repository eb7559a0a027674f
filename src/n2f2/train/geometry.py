"""The frozen Gaussians as training sees them: the training and held-out views, the cameras at
the segment bank's resolution, the detached Gaussian parameters, and the features rasterized
from them, down to theta(u) at a batch of sampled pixels."""

from __future__ import annotations

from typing import Any, Callable, Optional, Union

import torch
from torch import Tensor

from ..field.model import NestedField
from .blend import BlendCache
from .sampling import PixelBatch


def split_views(scene: Any, holdout: bool) -> tuple[list[int], list[int]]:
    """(train, held-out) views: scene.json's ``test_views`` are held out when ``holdout``."""
    if not holdout:
        return list(range(len(scene))), []
    from ..gaussians.fit import split_views as _split  # the one reader of scene.json's test_views

    return _split(scene, 0)


def bank_cameras(scene: Any, bank: Any) -> list:
    """The scene's cameras at the bank's resolution (segment masks are per bank pixel)."""
    return [
        c if (c.width, c.height) == (bank.width, bank.height) else c.scaled(bank.width, bank.height)
        for c in scene.cameras
    ]


def frozen_geometry(gaussians: Any, device: Union[str, torch.device]) -> dict[str, Tensor]:
    """Detached activated Gaussian parameters: the 3DGS is frozen while the field trains."""
    with torch.no_grad():
        return {
            "means": gaussians.means.detach().float().to(device).contiguous(),
            "quats": gaussians.quats.detach().float().to(device).contiguous(),
            "scales": gaussians.scales.detach().float().to(device).contiguous(),
            "opacities": gaussians.opacities.detach().float().to(device).contiguous(),
        }


def render_features(
    geometry: dict[str, Tensor],
    features: Tensor,  # [N, C]
    camera: Any,
) -> Tensor:  # -> [H * W, C]
    """Rasterize per-Gaussian ``features`` (gradients flow to them only)."""
    from ..render import rasterize

    out = rasterize(geometry["means"], geometry["quats"], geometry["scales"], geometry["opacities"], features, camera)
    return out.features.reshape(-1, features.shape[1])


def pixel_theta(
    field: NestedField,
    geometry: dict[str, Tensor],
    batch: PixelBatch,
    deferred: bool,
    cameras: Optional[list] = None,
    cache: Optional[BlendCache] = None,
    encoder: Optional[Callable[[], Tensor]] = None,
) -> Tensor:  # -> theta [P, D] for the batch's pixels
    """theta(u) at the sampled pixels. Slot k of the batch is ``cameras[k]`` (rasterized now) or
    the k-th view of ``cache`` (cached blending weights). ``encoder``: the field's
    :meth:`~n2f2.field.model.NestedField.fixed_point_encoder` of the Gaussian centres (built here
    when not given; a training loop builds it once).

    Deferred (training, paper): the backbone features [N, F] are blended and the MLP runs per
    pixel. Non-deferred (test-time form): the MLP runs per Gaussian and D channels are blended."""
    encoder = encoder or field.fixed_point_encoder(geometry["means"])
    per_gaussian = encoder() if deferred else field.decode(encoder())
    if cache is not None:
        rendered = cache.blend(per_gaussian, batch.slot, batch.pixel)  # [P, C]
    else:
        assert cameras is not None  # without a cache the batch's views are rasterized from these
        order, rows = [], []
        for k, cam in enumerate(cameras):
            sel = torch.nonzero(batch.slot == k).squeeze(1)  # [p] rows of the batch from view slot k
            if sel.numel() == 0:
                continue
            image = render_features(geometry, per_gaussian, cam)  # [H*W, C]
            order.append(sel)
            rows.append(image[batch.pixel[sel]])
        gathered = torch.cat(rows)  # [P, C] grouped by slot
        rendered = torch.empty_like(gathered)
        rendered[torch.cat(order)] = gathered  # back to batch order
    return field.decode(rendered) if deferred else rendered
