"""Atomic file output: every file is written to a temporary sibling, then renamed into place,
so an interrupted run never leaves a half-written file behind."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterable, Iterator, Optional

import numpy as np


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path in the same folder; on success it replaces ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_json(path: str | Path, obj: Any) -> None:
    write_text(path, json.dumps(obj, indent=2, default=_json_default) + "\n")


def write_npy(path: str | Path, array: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, array)


def save_torch(path: str | Path, obj: Any) -> None:
    import torch

    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def load_torch(path: str | Path, what: str = "file") -> Any:
    """Read a file written by :func:`save_torch`, on the CPU. ``weights_only``: tensors,
    numbers, strings and containers only, so a crafted file cannot run code when loaded.
    A file that cannot be read is one :class:`~n2f2.errors.InputError` line ("cannot read
    the ``what``: ...")."""
    import pickle

    import torch

    from .errors import InputError

    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        raise InputError(
            path,
            f"cannot read the {what}: it holds Python objects other than tensors and plain "
            "containers, which are refused without running them (n2f2 writes none)",
        ) from None
    except Exception as e:  # noqa: BLE001 - truncated or foreign files: the user's input problem
        reason = (str(e).strip().splitlines() or [""])[0]
        raise InputError(path, f"cannot read the {what} ({type(e).__name__}: {reason})") from None


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Write an 8-bit PNG from a uint8 array or a float array in [0, 1]. [H, W] or [H, W, 3|4]."""
    from PIL import Image

    if image.dtype != np.uint8:
        image = (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    with atomic_path(path) as tmp:
        Image.fromarray(image).save(tmp, format="PNG")


# The names atomic_path gives its temporary files: "." + name + "." + mkstemp's 8 random
# characters + ".tmp" + the name's suffix.
_TEMP_NAME = re.compile(r"^\..+\.[a-z0-9_]{8}\.tmp(\.[^/]*)?$")


def remove_orphaned_temp_files(folder: str | Path) -> list[Path]:
    """Delete the temporary files that atomic writes left in ``folder`` and its subfolders (one
    level down, e.g. ``test_views/``) when their process was killed mid-write
    (``.checkpoint.pt.x1y2z3w4.tmp.pt``). Returns what was removed."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    removed = []
    for path in [*folder.glob(".*.tmp*"), *folder.glob("*/.*.tmp*")]:
        if _TEMP_NAME.match(path.name) and path.is_file() and not path.is_symlink():
            with contextlib.suppress(FileNotFoundError):
                path.unlink()
                removed.append(path)
    return removed


def existing_results(out: str | Path, results: Iterable[str]) -> list[str]:
    """The names in ``results`` (files or folders inside ``out``) that exist."""
    out = Path(out)
    return [name for name in results if (out / name).exists()]


def claim_out_dir(
    out: str | Path,
    results: Iterable[str],
    *,
    resume: bool = False,
    force: bool = False,
    resume_flag: Optional[str] = "--resume",
) -> list[str]:
    """Open a command's ``--out`` folder before any work: remove orphaned temporary files, and
    refuse (one :class:`~n2f2.errors.InputError` naming the folder) when it already holds any
    of ``results`` unless the user asked to resume or to replace them (``--force``). Returns
    the results present (for :func:`remove_results` once the inputs are checked)."""
    from .errors import InputError

    out = Path(out)
    if resume and force:
        raise InputError(None, f"{resume_flag} continues the results in {out} and --force replaces them: pass one")
    if out.exists() and not out.is_dir():
        raise InputError(out, "output folder is a file")
    remove_orphaned_temp_files(out)
    present = existing_results(out, results)
    if present and not (resume or force):
        shown = ", ".join(present[:4]) + (f" and {len(present) - 4} more" if len(present) > 4 else "")
        offer = f"{resume_flag} to continue, or --force to replace them" if resume_flag else "--force to replace them"
        raise InputError(out, f"output folder already holds results ({shown}); pass {offer}, or choose another --out")
    return present


def remove_results(out: str | Path, names: Iterable[str]) -> None:
    """Delete results ``names`` (files or folders) of ``out``: what ``--force`` replaces, once
    the new run's inputs have been checked."""
    out = Path(out)
    for name in names:
        path = out / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
