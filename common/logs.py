"""Logging set-up shared by every process, and a helper for periodic reports."""

from __future__ import annotations

import logging
import sys
import time


def setup_logging(role: str, level: str = "INFO") -> logging.Logger:
    """One line per record on stderr: time, role, level, message."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter(f"%(asctime)s {role} %(levelname)s %(name)s: %(message)s", "%H:%M:%S"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
    return logging.getLogger(role)


class Every:
    """True once per period: paces logs and stats without a timer thread."""

    def __init__(self, period_s: float, clock=time.monotonic) -> None:
        self.period_s = period_s
        self._clock = clock
        self._last = clock()

    def due(self) -> bool:
        now = self._clock()
        if now - self._last >= self.period_s:
            self._last = now
            return True
        return False
