"""Memory of field training: activation bytes autograd saves per step
(:class:`ActivationMeter`), parameter bytes and counts, and the channels deferred rendering
rasterizes."""

from __future__ import annotations

import functools
import json
from typing import TYPE_CHECKING, Any, Optional, Sequence

import numpy as np

if TYPE_CHECKING:
    from torch.autograd.graph import saved_tensors_hooks


class ActivationMeter:
    """Bytes of the tensors autograd saves for backward, per optimisation step (the activation
    memory of training), measured with ``torch.autograd.graph.saved_tensors_hooks``.

    Storages are counted once per step; storages of ``exclude`` tensors (the parameters) are not
    activations and are skipped. :meth:`end_step` closes a step (called from the trainer's
    per-step callback)."""

    def __init__(self, exclude: Sequence[Any] = ()) -> None:
        self._exclude = {self._key(t) for t in exclude}
        self._seen: set = set()
        self._bytes = 0
        self.steps: list[int] = []
        self._ctx: Optional[saved_tensors_hooks] = None  # set by __enter__

    @staticmethod
    def _key(t: Any) -> int:
        return t.untyped_storage().data_ptr()

    def _pack(self, t: Any) -> Any:
        try:
            key = self._key(t)
        except (RuntimeError, NotImplementedError):  # e.g. tensors without a storage
            return t
        if key not in self._exclude and key not in self._seen:
            self._seen.add(key)
            self._bytes += t.untyped_storage().nbytes()
        return t

    def end_step(self, *_: Any) -> None:
        self.steps.append(self._bytes)
        self._seen.clear()
        self._bytes = 0

    @property
    def peak_bytes(self) -> int:
        return max(self.steps + [self._bytes])

    def __enter__(self) -> "ActivationMeter":
        import torch

        self._ctx = torch.autograd.graph.saved_tensors_hooks(self._pack, lambda t: t)
        self._ctx.__enter__()
        return self

    def __exit__(self, *exc: Any) -> None:
        assert self._ctx is not None  # __exit__ follows __enter__, which sets it
        self._ctx.__exit__(*exc)


def field_parameter_count(config: Any, embed_dim: int) -> int:
    """Trainable parameters of a field with ``config`` (built once per config and dropped: the
    paper-size TriPlane is ~200 MB for a moment). The variant and k do not change the count."""
    from ..field.model import FieldConfig

    shape = FieldConfig.from_dict({**config.to_dict(), "variant": "nested", "step_size": 1})
    return _parameter_count(json.dumps(shape.to_dict(), sort_keys=True), int(embed_dim))


@functools.lru_cache(maxsize=None)
def _parameter_count(config_json: str, embed_dim: int) -> int:
    from ..field.model import FieldConfig, NestedField

    field = NestedField(FieldConfig.from_dict(json.loads(config_json)), embed_dim, np.zeros(3), np.ones(3))
    return int(sum(p.numel() for p in field.parameters() if p.requires_grad))


def rasterized_channels(field_config: Any) -> int:
    """Channels deferred rendering rasterizes: the backbone's output (TriPlane channels, or the
    positional encoding's 3 + 6 L)."""
    if field_config.backbone == "triplane":
        return int(field_config.plane_channels)
    return 3 + 6 * int(field_config.pe_frequencies)
