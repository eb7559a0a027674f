"""glibc's large-block thresholds (n2f2.heap): in a fresh process, a 6 MB block freed and
allocated again is served from memory already mapped under the batch policy (no page faults),
and from a new mapping, faulted in page by page, under the server policy."""

from __future__ import annotations

import resource
import subprocess
import sys

import pytest

from n2f2.heap import BATCH_MMAP_THRESHOLD, BATCH_TRIM_THRESHOLD

BLOCK = 6 << 20  # below the batch mmap threshold, above the server's 1 MB
CYCLES = 10

# malloc, touch every byte, free; once to warm up, then CYCLES times counting minor page faults.
SCRIPT = f"""
import ctypes, ctypes.util, resource, sys
from n2f2.heap import keep_freed_blocks, return_freed_blocks
libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
libc.malloc.restype = ctypes.c_void_p
libc.malloc.argtypes = [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
libc.memset.argtypes = [ctypes.c_void_p, ctypes.c_int, ctypes.c_size_t]
ok = keep_freed_blocks() if sys.argv[1] == "keep" else return_freed_blocks(1 << 20)
def cycle():
    p = libc.malloc({BLOCK})
    libc.memset(p, 1, {BLOCK})
    libc.free(p)
cycle()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range({CYCLES}):
    cycle()
print(int(ok), resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _run(policy: str) -> tuple[bool, int]:  # (mallopt accepted the thresholds?, minor faults)
    out = subprocess.run([sys.executable, "-c", SCRIPT, policy], capture_output=True, text=True, check=True)
    ok, faults = out.stdout.split()
    return ok == "1", int(faults)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc")
def test_batch_policy_reuses_freed_blocks_and_server_policy_returns_them():
    returned, faults_returned = _run("return")
    if not returned:
        pytest.skip("glibc's mallopt is not available here")
    kept, faults_kept = _run("keep")
    assert kept  # glibc accepts the batch thresholds (it refuses an mmap threshold above 32 MB)
    assert BLOCK < BATCH_MMAP_THRESHOLD < BATCH_TRIM_THRESHOLD
    pages = BLOCK // resource.getpagesize()  # 1536 with 4 KB pages
    assert faults_kept < pages // 10  # the block is reused: nothing faulted in again
    assert faults_returned >= CYCLES * pages * 9 // 10  # a new mapping each time, every page faulted
