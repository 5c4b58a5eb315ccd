"""Give back to the system what a long run of HTTP reads leaves in glibc's heap (the soak's
creep: docs/RELIABILITY.md, "Soak").

asyncio's socket transport reads for a plain `Protocol` (aiohttp's client and server protocols
are such) with `sock.recv(256 KiB)` and shrinks the result to what arrived. glibc serves a
256 KiB request from mmap only until the first such block is freed: its *dynamic* mmap
threshold then rises above 256 KiB and every later read buffer is carved from the main heap,
shrunk in place, and the small reply left there pins the heap around it. At 1,200 calls in
flight the heap's free space fragments faster than it is reused: the soak grew ~1.9 MB/min
(~200 bytes per call) while the bytes in use stayed flat (malloc_stats: arena 0 in use
68.4 -> 68.3 MiB, taken from the system 72.9 -> 80.0 MiB over 3 minutes): no object leaked, the
heap did.

Fixing the threshold at 128 KiB (`mallopt(M_MMAP_THRESHOLD)`) stopped it (the 30-minute soak
at 0.075 MB/min), but it is process-wide: every allocation of 128 KiB or more then costs an
mmap, page faults and an munmap, and the embedded server's image decoding (a 1280x960 JPEG to
RGB and HSV) took 40-70 % longer with it. So instead a thread
returns the heap's free pages to the system every `TRIM_EVERY_S` (`malloc_trim(0)`, which
releases whole free pages inside the heap too, not only at its top): allocation stays as fast
as glibc makes it, and what fragmentation holds is given back. `keep_trimmed` starts it once
per process (the pool and the embedded server call it); a no-op off glibc.
"""

from __future__ import annotations

import ctypes
import sys
import threading
from collections.abc import Callable

TRIM_EVERY_S = 30.0
_trimmer: threading.Thread | None = None
_guard = threading.Lock()
_stop = threading.Event()  # set: the thread ends (tests); the process's exit ends it anyway


def _malloc_trim() -> Callable[[int], int] | None:
    if not sys.platform.startswith("linux"):
        return None
    try:
        fn = ctypes.CDLL(None).malloc_trim
    except (OSError, AttributeError):  # not glibc (musl has none)
        return None
    fn.argtypes = (ctypes.c_size_t,)
    fn.restype = ctypes.c_int
    return fn


MALLOC_TRIM = _malloc_trim()


def trim() -> bool:
    """Return the free pages of every malloc arena to the system now; True if any was."""
    return bool(MALLOC_TRIM(0)) if MALLOC_TRIM is not None else False


def keep_trimmed() -> bool:
    """Start this process's trimming thread, a trim every `TRIM_EVERY_S` (once; later calls
    return at once). False where glibc's malloc_trim is missing."""
    global _trimmer
    if MALLOC_TRIM is None:
        return False
    with _guard:
        if _trimmer is None or not _trimmer.is_alive():
            _trimmer = threading.Thread(
                target=_trim_forever, args=(TRIM_EVERY_S,), name="heap-trim", daemon=True
            )
            _trimmer.start()
    return True


def _trim_forever(every_s: float) -> None:
    while not _stop.wait(every_s):
        trim()
