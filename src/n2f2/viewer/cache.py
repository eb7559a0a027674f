"""The viewer's render cache: an LRU bounded in bytes, and the byte count of a rendered view (its
tensors' storages, each counted once)."""

from __future__ import annotations

from collections import OrderedDict
from typing import Any, Optional


def tensor_bytes(obj: Any, seen: Optional[set[int]] = None, exclude: frozenset[int] = frozenset()) -> int:
    """Bytes of the tensor storages reachable from ``obj`` (tensors, dataclasses, dicts, lists),
    each storage counted once: a view keeps its whole storage alive, so that is what it costs.
    ``exclude`` holds storage pointers owned elsewhere (the field's ``W``)."""
    import dataclasses

    import torch

    seen = set() if seen is None else seen
    if isinstance(obj, torch.Tensor):
        storage = obj.untyped_storage()
        ptr = storage.data_ptr()
        if ptr in seen or ptr in exclude:
            return 0
        seen.add(ptr)
        return int(storage.nbytes())
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return sum(tensor_bytes(getattr(obj, f.name), seen, exclude) for f in dataclasses.fields(obj))
    if isinstance(obj, dict):
        return sum(tensor_bytes(v, seen, exclude) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(tensor_bytes(v, seen, exclude) for v in obj)
    return 0


def compact_tensors(obj: Any, exclude: frozenset[int] = frozenset()) -> None:
    """Copy every tensor field of ``obj`` (a dataclass, and the dataclasses in its dict fields)
    that is a view into a larger storage, so that caching ``obj`` keeps only its own data (a
    rendered alpha map can be a slice of the rasterizer's whole output buffer)."""
    import dataclasses

    import torch

    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if isinstance(value, torch.Tensor):
            storage = value.untyped_storage()
            if storage.data_ptr() not in exclude and storage.nbytes() > value.numel() * value.element_size():
                setattr(obj, f.name, value.clone(memory_format=torch.contiguous_format))
        elif isinstance(value, dict):
            for v in value.values():
                if dataclasses.is_dataclass(v) and not isinstance(v, type):
                    compact_tensors(v, exclude)


class ByteLRU:
    """A least-recently-used map bounded by the total size of its values (``sizeof(value)``
    bytes each). A value larger than the whole bound is not stored. Not thread-safe: the
    Viewer's lock guards it."""

    def __init__(self, max_bytes: int, sizeof: Any):
        self.max_bytes = int(max_bytes)
        self.sizeof = sizeof
        self._items: OrderedDict[str, tuple[Any, int]] = OrderedDict()
        self.nbytes = 0

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, key: str) -> bool:
        return key in self._items

    def keys(self) -> list[str]:
        """Keys, least recently used first."""
        return list(self._items)

    def get(self, key: str) -> Any:
        """The value (now the most recently used) or None."""
        item = self._items.get(key)
        if item is None:
            return None
        self._items.move_to_end(key)
        return item[0]

    def reserve(self, nbytes: int) -> None:
        """Evict least-recently-used entries until ``nbytes`` more fit under the bound (or the
        cache is empty): room for a value being made, before it takes memory."""
        while self._items and self.nbytes + nbytes > self.max_bytes:
            _, (_, evicted) = self._items.popitem(last=False)
            self.nbytes -= evicted

    def put(self, key: str, value: Any) -> bool:
        """Store ``value``, evicting least-recently-used entries until it fits; False when it is
        larger than the bound (then nothing is evicted and it is not stored)."""
        size = int(self.sizeof(value))
        if size > self.max_bytes:
            return False
        old = self._items.pop(key, None)
        if old is not None:
            self.nbytes -= old[1]
        while self._items and self.nbytes + size > self.max_bytes:
            _, (_, evicted) = self._items.popitem(last=False)
            self.nbytes -= evicted
        self._items[key] = (value, size)
        self.nbytes += size
        return True
