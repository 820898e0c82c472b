"""Refused input counted by kind and logged at a bounded rate, for every role that checks what it receives."""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter

from common.logs import LOG_PERIOD_S, ThrottledLog


class Rejections:
    """Refused input by kind: counted, and logged at most once per kind per period by a ThrottledLog of
    its own (the next line of a kind says how many were not shown). Thread-safe: Zenoh calls back on
    several threads."""

    def __init__(self, logger: logging.Logger, period_s: float = LOG_PERIOD_S, clock=time.monotonic) -> None:
        self._log = logger
        self._period_s = period_s
        self._clock = clock
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self._lines: dict[str, ThrottledLog] = {}

    def reject(self, kind: str, text: str) -> None:
        with self._lock:
            self.counts[kind] += 1
            line = self._lines.get(kind)
            if line is None:
                line = self._lines[kind] = ThrottledLog(self._period_s, self._clock, self._log)
        line.warning("rejected (%s): %s", kind, text[:500])

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
