"""Refused input counted by kind and logged at a bounded rate, for every role that checks what it receives."""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter


class Rejections:
    """Refused input by kind: counted, and logged at most once per kind per period (the next line
    of a kind says how many were not shown). Thread-safe: Zenoh calls back on several threads."""

    def __init__(self, logger: logging.Logger, period_s: float = 10.0, clock=time.monotonic) -> None:
        self._log = logger
        self._period_s = period_s
        self._clock = clock
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self._last: dict[str, float] = {}
        self._unshown: Counter[str] = Counter()

    def reject(self, kind: str, text: str) -> None:
        with self._lock:
            self.counts[kind] += 1
            now = self._clock()
            if now - self._last.get(kind, -math.inf) < self._period_s:
                self._unshown[kind] += 1
                return
            self._last[kind] = now
            unshown, self._unshown[kind] = self._unshown[kind], 0
        more = f" ({unshown} more of this kind since the last line)" if unshown else ""
        self._log.warning("rejected (%s): %s%s", kind, text[:500], more)

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self.counts.values())

    def values(self, prefix: str = "rejected_") -> dict[str, int]:
        """{prefix + kind: count} and {prefix + "total": sum}, for a Stats message."""
        with self._lock:
            counts = dict(self.counts)
        return {**{f"{prefix}{kind}": count for kind, count in sorted(counts.items())},
                f"{prefix}total": sum(counts.values())}
