"""Keeps freed memory in the learner process for reuse, instead of handing it back to the OS.

Every backward pass allocates the 44 MB gradient of the LSTM input weights
afresh. glibc serves blocks above 32 MB with mmap and unmaps them when freed,
so each update pays ~11,000 page faults to get that memory back, zeroed by the
kernel. Measured at the paper's sizes on the 2-core CPU, the one-pass update
runs 10-18% faster with mmap off and trimming raised (deploy/bench/learner_speed.py).
"""

from __future__ import annotations

import ctypes
import ctypes.util

# mallopt parameters, from glibc's malloc.h
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4

TRIM_THRESHOLD_BYTES = 2**30  # free heap top kept up to this much before it is returned


def keep_freed_memory() -> bool:
    """Serves large blocks from the heap and keeps them after free; False where libc has no mallopt (not glibc)."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return bool(mallopt(M_MMAP_MAX, 0)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES))
