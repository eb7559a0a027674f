"""One serialisation rule for the config dataclasses (``FitConfig``, ``FieldConfig``,
``TrainConfig``): they are saved as JSON in checkpoints and reports and read back with
:meth:`ConfigDict.from_dict`, and the named presets (``cpu``, ``paper``) are their static
constructors of the same name."""

from __future__ import annotations

from dataclasses import asdict, fields
from typing import Any, ClassVar, TypeVar

T = TypeVar("T", bound="ConfigDict")


class ConfigDict:
    """Mixin for config dataclasses: ``to_dict``, ``from_dict`` and ``preset``."""

    PRESETS: ClassVar[tuple[str, ...]] = ()  # names of static constructors, e.g. ("cpu", "paper")

    def to_dict(self) -> dict:
        return asdict(self)  # type: ignore[call-overload]

    @classmethod
    def from_dict(cls: type[T], d: dict) -> T:
        """Rebuild from :meth:`to_dict`'s output. Keys this version does not know are ignored (a
        checkpoint from another version still loads), and JSON lists become tuples again."""
        known = {f.name for f in fields(cls)}  # type: ignore[arg-type]
        kw: dict[str, Any] = {k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items() if k in known}
        return cls(**kw)

    @classmethod
    def preset(cls: type[T], name: str) -> T:
        if name not in cls.PRESETS:
            raise ValueError(f"unknown preset {name!r}; choose from {sorted(cls.PRESETS)}")
        return getattr(cls, name)()
