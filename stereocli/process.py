"""Process-wide settings, applied by the entry points (the command line, benchmarks), never by
importing the library.

:func:`keep_freed_memory` keeps freed large buffers in the process (glibc ``mallopt``), so
matching does not pay for fresh pages on every pair.

Each pair allocates and frees tens of MiB (cost volumes, path sums, maps). glibc serves blocks
above ``M_MMAP_THRESHOLD`` (128 KiB, rising to at most 32 MiB) with fresh ``mmap`` pages and
returns them on ``free``, so the next pair touches new pages again: on the benchmark machine
that was 1,500–5,000 page faults and 10–25 ms per MiddEval3 Q pair, as much as OpenCV's whole
SGBM (which keeps its buffers inside the matcher object between calls). Raising both
thresholds keeps the blocks on the heap for reuse. The price is that RSS stays near the peak
between pairs instead of dropping.

Applied once by ``stereocli`` at start-up; set ``STEREOCLI_KEEP_FREED_MEMORY=0`` to leave the
allocator alone. A no-op where the C library has no ``mallopt`` (non-glibc).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: Blocks up to this size come from the heap, and the heap keeps this much free memory.
KEEP_BYTES = 1 << 30

_applied: bool | None = None


def keep_freed_memory() -> bool:
    """Apply the thresholds (once); True if the C library accepted them."""
    global _applied
    if _applied is not None:
        return _applied
    _applied = False
    if os.environ.get("STEREOCLI_KEEP_FREED_MEMORY", "1") == "0":
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    _applied = bool(mallopt(_M_MMAP_THRESHOLD, KEEP_BYTES)) and bool(mallopt(_M_TRIM_THRESHOLD, KEEP_BYTES))
    return _applied
