"""Keep glibc from growing the heap under a long run of HTTP reads (the soak's creep, issue 36).

asyncio's socket transport reads for a plain `Protocol` (aiohttp's client and server protocols
are such) with `sock.recv(256 KiB)` and shrinks the result to what arrived. glibc serves a
256 KiB request from mmap only until the first such block is freed: its *dynamic* mmap
threshold then rises above 256 KiB and every later read buffer is carved from the main heap,
shrunk in place, and the small reply left there pins the heap around it. At 1,200 calls in
flight the heap's free space fragments faster than it is reused: the soak grew ~1.9 MB/min
(~200 bytes per call) while the bytes in use stayed flat (malloc_stats: arena 0 in use
68.4 -> 68.3 MiB, taken from the system 72.9 -> 80.0 MiB over 3 minutes): no object leaked, the
heap did.

Fixing the threshold at glibc's default of 128 KiB (`mallopt(M_MMAP_THRESHOLD)`, what the
environment variable MALLOC_MMAP_THRESHOLD_=131072 does at start-up) keeps every read buffer in
its own mapping, returned whole when freed; the cost is an mmap and munmap per read. Measured:
the 30-minute soak's RSS slope 0.075 MB/min (docs/RELIABILITY.md, "Soak"). Process-wide,
once; a no-op off glibc, or where the user set the variable (theirs to choose).
"""

from __future__ import annotations

import ctypes
import os
import sys

M_MMAP_THRESHOLD = -3  # <malloc.h>
READ_BUFFER_THRESHOLD = 128 * 1024  # glibc's default; below asyncio's 256 KiB read buffer
_fixed = False


def fix_mmap_threshold(nbytes: int = READ_BUFFER_THRESHOLD) -> bool:
    """Fix glibc's mmap threshold at `nbytes` for this process (once); True if it is fixed."""
    global _fixed
    if _fixed or "MALLOC_MMAP_THRESHOLD_" in os.environ:
        return _fixed
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc (musl has no tunable threshold)
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    _fixed = bool(mallopt(M_MMAP_THRESHOLD, nbytes))
    return _fixed
