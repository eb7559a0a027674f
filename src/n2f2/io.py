"""Output folders and atomic file output.

Every file is written to a temporary sibling, then renamed into place, so an interrupted run
never leaves a half-written file behind. A command's ``--out`` folder is claimed before any
heavy work (:func:`claim_out_dir`): it must be a folder that can be created and written, with
room to spare, and it is locked (``OUT/.n2f2.lock``) so that one run at a time writes into it.

Inside :func:`command_outputs` (the CLI wraps every command in it) the files a command writes
form one set: a command that fails (a full or read-only disk, bad input found late, a bug,
Ctrl-C) puts the folder back as it was, removing the results it wrote, restoring the ones it
replaced and the folders it created. Resumable state (checkpoints, segment-bank records) is
kept, so ``--resume`` continues after the cause is fixed. A long command publishes what is
complete with :func:`commit_outputs` (``n2f2 run`` after each stage).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import re
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Optional

import numpy as np

# Errors of the disk rather than of the program: reported as one line naming the file.
DISK_ERRNOS = frozenset({errno.ENOSPC, errno.EROFS, errno.EIO, errno.EDQUOT, errno.EACCES, errno.EPERM, errno.EFBIG})


def output_error(path: str | Path, err: OSError, detail: str = ""):
    """The one-line :class:`~n2f2.errors.OutputError` for a write to ``path`` that failed."""
    from .errors import OutputError

    reason = os.strerror(err.errno) if err.errno else str(err)
    return OutputError(path, f"cannot write ({reason[:1].lower()}{reason[1:]}{detail})")


@contextlib.contextmanager
def atomic_path(path: str | Path, keep: bool = False) -> Iterator[Path]:
    """Yield a temporary path in the same folder; on success it replaces ``path``. A write the
    disk refuses (full, read-only, I/O error) is an :class:`~n2f2.errors.OutputError` naming
    ``path``, with the temporary file removed. Inside :func:`command_outputs` the new file is
    journaled (removed, or the file it replaced restored, if the command fails) unless
    ``keep`` (resumable state such as checkpoints)."""
    path = Path(path)
    tmp_path: Optional[Path] = None
    try:
        make_dirs(path.parent)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
        os.close(fd)
        tmp_path = Path(tmp)
        yield tmp_path
        if _JOURNAL is not None and not keep:
            _JOURNAL.before_replace(path)
        os.replace(tmp_path, path)
    except OSError as e:
        if e.filename is not None and not _ours(Path(str(e.filename)), path):
            raise  # another file (an input being copied): its own error, naming it
        if e.errno in DISK_ERRNOS:
            raise output_error(path, e) from None
        if e.errno is None and "written" in str(e):  # numpy's short write ("4800 requested and 3040 written")
            free = shutil.disk_usage(path.parent).free
            raise output_error(path, OSError(errno.ENOSPC, ""), f": {free >> 10} kB free") from None
        raise
    finally:
        if tmp_path is not None and tmp_path.exists():
            with contextlib.suppress(OSError):
                tmp_path.unlink()


def _ours(name: Path, path: Path) -> bool:
    """``name`` is ``path``, a sibling of it (its temporary file) or one of its folders."""
    return name.parent == path.parent or name == path.parent or name in path.parents


def make_dirs(folder: str | Path) -> None:
    """``mkdir -p``; inside :func:`command_outputs` the folders made are removed again (when
    empty) if the command fails."""
    folder = Path(folder)
    if folder.is_dir():
        return
    missing = []
    for p in (folder, *folder.parents):
        if p.exists():
            break
        missing.append(p)
    folder.mkdir(parents=True, exist_ok=True)
    if _JOURNAL is not None:
        _JOURNAL.created_dirs.extend(reversed(missing))


def write_bytes(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text(path: str | Path, text: str, keep: bool = False) -> None:
    with atomic_path(path, keep=keep) as tmp:
        tmp.write_text(text)


def write_json(path: str | Path, obj: Any, keep: bool = False) -> None:
    """``obj`` as indented JSON, atomically (``keep``: see :func:`atomic_path`)."""
    write_text(path, json.dumps(obj, indent=2, default=_json_default) + "\n", keep=keep)


def write_npy(path: str | Path, array: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, array)


def save_torch(path: str | Path, obj: Any, keep: bool = False) -> None:
    """``torch.save`` atomically (``keep``: see :func:`atomic_path`). torch reports a full disk
    as a ``RuntimeError`` of its zip writer; that becomes the same one-line error."""
    import torch

    with atomic_path(path, keep=keep) as tmp:
        try:
            torch.save(obj, tmp)
        except RuntimeError as e:
            if "inline_container" not in str(e) and "file write failed" not in str(e):
                raise
            free = shutil.disk_usage(Path(path).parent).free
            raise output_error(path, OSError(errno.ENOSPC, ""), f": {free >> 20} MB free") from None


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
    # Earlier results a killed command had set aside (--force): back in place when nothing
    # replaced them, else dropped.
    for path in folder.glob(".*.n2f2-old-*"):
        match = _ASIDE_NAME.match(path.name)
        if match is None or _pid_alive(int(match[2])):
            continue
        original = path.with_name(match[1])
        with contextlib.suppress(OSError):
            if original.exists() or original.is_symlink():
                _remove(path)
                removed.append(path)
            else:
                os.rename(path, original)
    return removed


_ASIDE_NAME = re.compile(r"^\.(.+)\.n2f2-old-(\d+)$")


# Space a claimed folder must have free, besides what a command says it needs (MB; the
# environment variable N2F2_MIN_FREE_MB sets another floor).
MIN_FREE_BYTES = 16 << 20


def min_free_bytes() -> int:
    value = os.environ.get("N2F2_MIN_FREE_MB")
    try:
        return MIN_FREE_BYTES if value is None else max(0, int(float(value) * 2**20))
    except ValueError:
        return MIN_FREE_BYTES


LOCK_NAME = ".n2f2.lock"


def claim_out_dir(
    out: str | Path,
    results: Iterable[str],
    *,
    resume: bool = False,
    force: bool = False,
    resume_flag: Optional[str] = "--resume",
    need_bytes: int = 0,
) -> list[str]:
    """Open a command's ``--out`` folder before any work: check that it can be created and
    written with room to spare (``need_bytes``, an estimate of what the command writes, plus
    :func:`min_free_bytes`), lock it for this process (:func:`lock_out_dir`), remove orphaned
    temporary files, and refuse when it already holds any of ``results`` unless the user asked
    to resume or to replace them (``--force``). Every refusal is one
    :class:`~n2f2.errors.InputError` naming the folder. Returns the results present (for
    :func:`remove_results` once the inputs are checked)."""
    from .errors import InputError

    out = Path(out)
    if resume and force:
        raise InputError(None, f"{resume_flag} continues the results in {out} and --force replaces them: pass one")
    check_writable_dir(out, need_bytes)
    lock_out_dir(out)
    remove_orphaned_temp_files(out)  # only now: a live run's temporary files are its own
    present = existing_results(out, results)
    if present and not (resume or force):
        shown = ", ".join(present[:4]) + (f" and {len(present) - 4} more" if len(present) > 4 else "")
        offer = f"{resume_flag} to continue, or --force to replace them" if resume_flag else "--force to replace them"
        raise InputError(out, f"output folder already holds results ({shown}); pass {offer}, or choose another --out")
    return present


def check_writable_dir(out: str | Path, need_bytes: int = 0) -> None:
    """Create ``out`` (and its parents) if needed and prove it writable with a small file; one
    :class:`~n2f2.errors.InputError` naming the folder otherwise (``not a directory``,
    ``read-only``, ``not writable``, ``no space left: N MB free, about M MB needed``)."""
    from .errors import InputError

    out = Path(out)
    for p in (out, *out.parents):  # the first existing component must be a folder
        if p.exists() or p.is_symlink():
            if not p.is_dir():
                raise InputError(
                    p, "output folder: not a directory" if p == out else f"not a directory (in --out {out})"
                )
            break
    try:
        make_dirs(out)
        fd, probe = tempfile.mkstemp(prefix=".n2f2-probe.", dir=out)
        try:
            os.write(fd, b"\0" * 4096)
            os.fsync(fd)
        finally:
            os.close(fd)
            os.unlink(probe)
    except OSError as e:
        reasons = {
            errno.EROFS: "read-only file system",
            errno.EACCES: "not writable (permission denied)",
            errno.EPERM: "not writable (operation not permitted)",
            errno.ENOSPC: "no space left on the device",
        }
        raise InputError(out, f"output folder: {reasons.get(e.errno or 0, e.strerror or str(e))}") from None
    free = shutil.disk_usage(out).free
    need = need_bytes + min_free_bytes()
    if free < need:
        raise InputError(
            out, f"output folder: no space left: {free / 2**20:.0f} MB free, about {need / 2**20:.0f} MB needed"
        )


# -- one run at a time per folder
@dataclass
class _Lock:
    fd: int
    path: Path


_LOCKS: dict[str, _Lock] = {}


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def lock_out_dir(out: str | Path) -> None:
    """Hold ``OUT/.n2f2.lock`` (``fcntl.flock``, holding the PID) until :func:`release_out_dirs`
    or the process ends. A folder this process already holds is fine; one held by a live
    process is an :class:`~n2f2.errors.InputError` naming its PID; a lock file left by a process
    that died is taken over, saying so on stderr."""
    from .errors import InputError

    out = Path(out)
    key = os.path.realpath(out)
    if key in _LOCKS:
        return
    path = out / LOCK_NAME
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_pid(fd)
            os.close(fd)
            who = f"PID {holder}" if holder else "another process"
            raise InputError(
                out, f"another n2f2 run ({who}) is writing to this folder; wait for it or choose another --out"
            ) from None
        # The holder before us may have removed the file after we opened it: lock the file
        # that is there now.
        try:
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    stale = _read_pid(fd)
    if stale and stale != os.getpid() and not _pid_alive(stale):
        import sys

        print(f"n2f2: {out}: taking over the lock of PID {stale}, which is no longer running", file=sys.stderr)
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    _LOCKS[key] = _Lock(fd, path)


def _read_pid(fd: int) -> int:
    try:
        return int(os.pread(fd, 32, 0).decode().strip() or 0)
    except (OSError, ValueError):
        return 0


def release_out_dirs() -> None:
    """Release every folder lock this process holds (removing the lock files)."""
    for lock in _LOCKS.values():
        with contextlib.suppress(OSError):
            os.unlink(lock.path)  # before unlocking: a waiter then finds the file gone and retries
        os.close(lock.fd)
    _LOCKS.clear()


# -- the journal of one command's outputs
@dataclass
class _Journal:
    created: list[Path] = field(default_factory=list)  # files that did not exist before
    replaced: list[tuple[Path, Path]] = field(default_factory=list)  # (result, its earlier version aside)
    created_dirs: list[Path] = field(default_factory=list)
    seen: set[str] = field(default_factory=set)

    def before_replace(self, path: Path) -> None:
        """``path`` is about to be (re)written: remember how to undo it, once per path."""
        key = os.path.realpath(path)
        if key in self.seen:
            return
        self.seen.add(key)
        if path.exists() and path.is_file():
            aside = _aside_name(path)
            try:
                os.link(path, aside)  # a second name for the old file: no copy, no space
            except OSError:
                return  # no hard links here: the old file cannot be kept
            self.replaced.append((path, aside))
        else:
            self.created.append(path)

    def set_aside(self, path: Path) -> None:
        """Move ``path`` (a file or folder being replaced by ``--force``) aside."""
        aside = _aside_name(path)
        os.rename(path, aside)
        self.seen.add(os.path.realpath(path))
        self.replaced.append((path, aside))

    def _forget(self) -> None:
        self.created.clear()
        self.replaced.clear()
        self.created_dirs.clear()
        self.seen.clear()

    def commit(self) -> None:
        for _, aside in self.replaced:
            _remove(aside)
        self._forget()

    def rollback(self) -> None:
        for path in reversed(self.created):
            with contextlib.suppress(OSError):
                _remove(path)
        for path, aside in reversed(self.replaced):
            with contextlib.suppress(OSError):
                if path.exists() or path.is_symlink():
                    _remove(path)
                os.rename(aside, path)
        for folder in reversed(self.created_dirs):
            with contextlib.suppress(OSError):
                for lock in [lk for k, lk in _LOCKS.items() if Path(k) == Path(os.path.realpath(folder))]:
                    lock.path.unlink(missing_ok=True)
                folder.rmdir()  # only when empty: resumable state stays
        self._forget()


def _aside_name(path: Path) -> Path:
    return path.with_name(f".{path.name}.n2f2-old-{os.getpid()}")


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif path.exists() or path.is_symlink():
        path.unlink()


_JOURNAL: Optional[_Journal] = None


@contextlib.contextmanager
def command_outputs() -> Iterator[None]:
    """Run one command's writes as a set: on success what it wrote stays (and the results it
    replaced go); on any failure the folders are put back as they were (resumable state kept).
    Folder locks are released at the end either way."""
    global _JOURNAL
    outer, _JOURNAL = _JOURNAL, _Journal()
    journal = _JOURNAL
    try:
        yield
        journal.commit()
    except BaseException:
        journal.rollback()
        raise
    finally:
        _JOURNAL = outer
        if outer is None:
            release_out_dirs()


def commit_outputs() -> None:
    """Publish what the current command has written so far (a finished stage of a long command):
    a later failure no longer removes it."""
    if _JOURNAL is not None:
        _JOURNAL.commit()


def existing_results(out: str | Path, results: Iterable[str]) -> list[str]:
    """The names in ``results`` (files or folders inside ``out``) that exist."""
    out = Path(out)
    return [name for name in results if (out / name).exists()]


def remove_results(out: str | Path, names: Iterable[str]) -> None:
    """Delete results ``names`` (files or folders) of ``out``: what ``--force`` replaces, once
    the new run's inputs have been checked. Inside :func:`command_outputs` they are moved aside
    instead, and only deleted when the command succeeds."""
    out = Path(out)
    for name in names:
        path = out / name
        if not (path.exists() or path.is_symlink()):
            continue
        if _JOURNAL is not None:
            _JOURNAL.set_aside(path)
        else:
            _remove(path)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
