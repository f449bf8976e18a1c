"""Process-wide heap settings for programs that check trajectories (no rclpy).

With glibc's defaults the sample arrays a check frees go back to the kernel, so the next check
faults every page in again. :func:`retain_freed_memory` keeps a bounded amount of freed memory
mapped instead. It changes the whole process, so only programs call it (the dyn_node and
dyn-audit entry points, the benchmark), never the library. Figures: docs/INTERNALS.md.
"""
from __future__ import annotations

import ctypes
import ctypes.util

# glibc's mallopt parameter numbers (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

#: Freed memory glibc keeps mapped (bytes): more than a 10,000-sample 7-joint check needs, less
#: than a 100,000-sample one, after which glibc trims as usual.
DEFAULT_KEEP_BYTES = 64 << 20
#: Blocks up to this size come from the heap (glibc's own dynamic threshold stops at 32 MiB).
DEFAULT_HEAP_BLOCK_BYTES = 32 << 20


def retain_freed_memory(keep_bytes: int = DEFAULT_KEEP_BYTES,
                        heap_block_bytes: int = DEFAULT_HEAP_BLOCK_BYTES) -> bool:
    """Set glibc's trim and mmap thresholds (bytes) for this process; True when applied.

    False, and nothing changed, where the C library is not glibc (no ``mallopt``) or refuses a
    value. Idempotent. Applies to every thread's arena, so a check on a worker thread benefits.
    """
    if keep_bytes < 0 or heap_block_bytes < 0:
        raise ValueError("byte counts must be non-negative")
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else ctypes.CDLL(None)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    limit = 2 ** 31 - 1      # mallopt takes an int
    return bool(mallopt(_M_MMAP_THRESHOLD, min(heap_block_bytes, limit))
                and mallopt(_M_TRIM_THRESHOLD, min(keep_bytes, limit)))
