"""Lazy package exports: the CLI imports every stage package to register its commands, and a
stage's names (which pull in torch) should load only when used. One helper for all stages."""

from __future__ import annotations

import importlib
from typing import Callable


def lazy_exports(package: str, exports: dict[str, str]) -> tuple[Callable[[str], object], list[str]]:
    """``exports`` maps a public name to the submodule that defines it. Returns the package's
    ``__getattr__`` (PEP 562) and ``__all__``."""

    def __getattr__(name: str):
        if name in exports:
            return getattr(importlib.import_module(f".{exports[name]}", package), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    return __getattr__, sorted(exports)
