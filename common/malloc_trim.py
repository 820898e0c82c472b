"""Hands the C heap's free pages back to the system (glibc's malloc_trim).

glibc keeps what a process frees for reuse, and gives its main heap back only from the top. A burst of
allocations, such as an actor's random phase at 1,000 env steps/s with its frames made and freed by the
thousand, leaves the process holding its peak for good: an actor of the grid read 1,479 MB of RSS, and
701 MB after one malloc_trim(0); the learner, the replay and the recorder each gave about 90 MB back.
A C library without the call (musl, macOS) is said in one log line; the process then keeps its peak.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import threading

log = logging.getLogger(__name__)


@functools.cache
def _malloc_trim():
    try:
        trim = ctypes.CDLL(None).malloc_trim  # the C library this process already runs on
    except (OSError, AttributeError):
        log.info("this C library has no malloc_trim (it is not glibc): memory freed after a burst stays "
                 "with the process")
        return None
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return trim


def release_free_heap() -> bool | None:
    """Gives the heap's free pages back: whether any went (glibc's answer), None without malloc_trim."""
    trim = _malloc_trim()
    return None if trim is None else bool(trim(0))


TRIM_PERIOD_S = 60.0  # a trim walks the heap under its lock: rare enough to cost nothing, often enough to matter


def keep_releasing_free_heap(stop: threading.Event) -> threading.Thread:
    """A thread that gives the heap's free pages back every TRIM_PERIOD_S until stop is set."""
    def trim() -> None:
        while not stop.wait(TRIM_PERIOD_S) and release_free_heap() is not None:
            pass

    thread = threading.Thread(target=trim, name="heap-trim", daemon=True)
    thread.start()
    return thread
