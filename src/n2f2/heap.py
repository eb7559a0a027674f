"""glibc's thresholds for large blocks, chosen by the kind of process.

glibc serves a block of ``M_MMAP_THRESHOLD`` bytes or more with a mapping of its own, unmapped
when the block is freed, and returns free memory above ``M_TRIM_THRESHOLD`` at the heap's top to
the system. Either way the next block of that size is new memory, which the kernel maps and
zero-fills page by page as it is first touched. By default both thresholds start at 128 KB and
rise only as large blocks are freed (up to 32 and 64 MB on 64-bit systems).

* Batch work (fitting, training, evaluating) allocates and frees the same large tensors every
  step: a TriPlane's texel gradient, rasterizer buffers. :func:`keep_freed_blocks` fixes the
  thresholds at glibc's own largest dynamic values from the start, so those blocks are reused
  from the heap instead of faulted in anew (docs/measurements.md, "Large blocks kept in the
  heap").
* A long-running server wants the opposite: :func:`return_freed_blocks` gives large freed blocks
  back, so its resident memory follows what it holds.

Setting either threshold turns glibc's dynamic adjustment off for both. Both functions return
False, changing nothing, where glibc is not the C library.
"""

from __future__ import annotations

M_TRIM_THRESHOLD = -1  # mallopt parameters (malloc.h)
M_MMAP_THRESHOLD = -3
BATCH_MMAP_THRESHOLD = 32 << 20  # glibc's largest dynamic mmap threshold on 64-bit systems
BATCH_TRIM_THRESHOLD = 64 << 20  # twice it, as glibc's dynamic rule sets the trim threshold


def set_thresholds(mmap_threshold: int, trim_threshold: int) -> bool:
    """``mallopt`` both thresholds (bytes); False where glibc is not the C library."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(M_TRIM_THRESHOLD, int(trim_threshold))) and bool(mallopt(M_MMAP_THRESHOLD, int(mmap_threshold)))


def keep_freed_blocks() -> bool:
    """Batch processes: freed blocks below 32 MB stay in the heap for the next step."""
    return set_thresholds(BATCH_MMAP_THRESHOLD, BATCH_TRIM_THRESHOLD)


def return_freed_blocks(threshold: int = 1 << 20) -> bool:
    """Servers: every block of ``threshold`` bytes or more is returned to the system when freed
    (its own mapping), and free heap above ``threshold`` is trimmed."""
    return set_thresholds(threshold, threshold)
