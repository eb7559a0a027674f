"""What every numba kernel of n2f2 shares: numba's threading layer, one lock, the kernels'
thread count, their fast-math flags, and compiling them ahead in a child process.

The kernels live in their own modules (the rasterizer's :mod:`n2f2.render.numba_backend` and
the modules it uses, the fit's :mod:`n2f2.gaussians.numba_adam` and
:mod:`n2f2.gaussians.numba_ssim`, ...); this module imports none of them, so every one of them
can import it.

Calls are serialised by :data:`KERNEL_LOCK`: the thread pool used here does not allow two
Python threads inside a parallel region at once.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import torch

try:  # optional at import time: the "auto" backend falls back to torch without it
    import numba
    from numba.core import config as numba_config
except ImportError:  # pragma: no cover - numba is a declared dependency
    numba = None
else:
    # numba's OpenMP layer leaves its threads spinning after each kernel, which slows the torch
    # operations around it several times over; the plain thread pool does not spin.
    if "NUMBA_THREADING_LAYER" not in os.environ:
        # numba fills its config module from the environment at import time, so stubs lack the names.
        numba_config.THREADING_LAYER = "workqueue"  # pyright: ignore[reportAttributeAccessIssue]

KERNEL_LOCK = threading.Lock()
# Reassociation lets the loops over channels vectorise; no flag that assumes finite values.
FASTMATH = {"reassoc", "contract", "nsz", "arcp"}


def numba_usable() -> bool:
    """True when the kernels can run here (numba imports)."""
    return numba is not None


_KERNEL_THREADS: int | None = None  # the kernels' threads while torch_on_one_thread() runs


def kernel_threads() -> int:
    """The threads the compiled kernels run on: torch's thread count, or the count torch had
    when :func:`torch_on_one_thread` began."""
    return _KERNEL_THREADS or torch.get_num_threads()


@contextmanager
def torch_on_one_thread() -> Iterator[None]:
    """torch's own operations on one thread meanwhile, the compiled kernels on the threads torch
    had. A loop that alternates many small torch operations with the kernels (a fit step: about
    30 of them around the render and its backward) otherwise has two thread pools taking turns
    on the same cores: torch's OpenMP threads spin after each operation (``GOMP_SPINCOUNT``)
    while the kernels' threads start (timings: ``docs/measurements.md``, "The fit's torch
    operations on one thread")."""
    global _KERNEL_THREADS
    if numba is None:  # the render is torch's own operations then: they keep torch's threads
        yield
        return
    before, torch_threads = _KERNEL_THREADS, torch.get_num_threads()
    _KERNEL_THREADS = kernel_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(torch_threads)
        _KERNEL_THREADS = before


def numba_threads() -> int:
    """Set numba's thread count to :func:`kernel_threads` (at most numba's pool) and return it,
    the ``nthreads`` a parallel kernel splits its work by; called holding :data:`KERNEL_LOCK`."""
    assert numba is not None  # only called beside the kernels, which exist only when numba imports
    # NUMBA_NUM_THREADS is set in numba's config module from the environment at import time.
    n_numba = numba_config.NUMBA_NUM_THREADS  # pyright: ignore[reportAttributeAccessIssue]
    n = max(1, min(kernel_threads(), n_numba))
    numba.set_num_threads(n)
    return n


# ------------------------------------------------------------------------------ compiling ahead
# Compiling the kernels takes ~20 s on 2 cores, once per install (then they load from the disk
# cache in under a second). A pipeline starts that compile in a child process while it does
# work that does not render (generating or reading the scene), and its first render waits until
# the child has compiled what the fit uses, so the kernels are compiled once and the compile
# overlaps that work; the child goes on with the later stages' kernels while the fit runs.
_BACKGROUND: subprocess.Popen | None = None
_STARTED = False  # a process starts at most one child (run-many calls the pipeline per scene)
_READY = b"rasterizer compiled"  # the child's line once the first render may go on


def compile_in_background(first: Sequence[str] = (), later: Sequence[str] = ()) -> None:
    """Start :func:`n2f2.render.numba_warm_up.warm_up` in a child process, once per process
    (nothing without numba), then the ``warm_up()`` of each module in ``first`` (dotted names:
    kernels the first renders' stage uses too, such as the fit's optimiser), then of each in
    ``later`` (kernels of later stages). The first compiled render waits until the child has
    compiled ``first`` (:func:`wait_for_background_compile`), not for ``later``, which the child
    compiles meanwhile so that those stages find their kernels cached."""
    global _BACKGROUND, _STARTED
    if _STARTED or numba is None:
        return
    _STARTED = True
    steps = [f"import {m}; {m}.warm_up()" for m in ("n2f2.render.numba_warm_up", *first)]
    steps += [f"print({_READY.decode()!r}, flush=True)"] + [f"import {m}; {m}.warm_up()" for m in later]
    try:
        _BACKGROUND = subprocess.Popen(
            [sys.executable, "-c", "; ".join(steps)], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL
        )
    except OSError:  # no child process here: the first render compiles, as without this
        _BACKGROUND = None


def wait_for_background_compile() -> int | None:
    """Wait until the child of :func:`compile_in_background` has compiled the rasterizer (and its
    ``first`` modules): 0 then, the child's exit code when it ended before (a failed child only
    means this process compiles what it needs itself), None when no child runs."""
    global _BACKGROUND
    child, _BACKGROUND = _BACKGROUND, None
    if child is None:
        return None
    assert child.stdout is not None  # started with a pipe
    with child.stdout:  # the child prints nothing after its one line
        ready = child.stdout.readline().strip() == _READY
    return 0 if ready else child.wait()
