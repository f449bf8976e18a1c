"""Process-wide heap settings for programs that check trajectories (no rclpy).

A feasibility check builds a few dozen sample arrays of N×nv doubles (560 KB each at 10,000
samples of 7 joints) and frees them at the end. With glibc's defaults, memory freed at the top
of the heap beyond a small threshold goes back to the kernel, so the next check takes every page
again as a fresh page fault. On the virtual machines this project runs on, a minor fault costs
1-8 µs, and a 10,000-sample check made about 3,300 of them: 3-14 ms on a 42-54 ms check
(three ``make bench`` runs, each way in a fresh process).

:func:`retain_freed_memory` asks glibc to keep up to ``keep_bytes`` of freed memory mapped, and
to serve blocks up to ``heap_block_bytes`` from the heap rather than from their own mmap. That
trades a bounded amount of resident memory after a large check for checks that touch no fresh
pages. It changes the whole process, so only programs call it (the dyn_node and dyn-audit entry
points, and the benchmark that measures the check as the node runs it), never the library.
"""
from __future__ import annotations

import ctypes
import ctypes.util

# glibc's mallopt parameter numbers (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

#: Freed memory glibc keeps mapped (bytes). A 10,000-sample 7-joint check leaves about 17 MiB
#: resident for the next one; a 100,000-sample check peaks near 180 MiB, more than this, so
#: glibc trims as usual afterwards and the process returns to its size before the check.
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
