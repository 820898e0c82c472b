"""Logging set-up shared by every process, and the helpers that pace lines: Every (once per period) and
ThrottledLog (at most once per period, counting what it held back)."""

from __future__ import annotations

import contextlib
import faulthandler
import logging
import sys
import threading
import time
from typing import Any, Callable

LOG_PERIOD_S = 10.0  # at most one warning of a kind per period per entity

log = logging.getLogger(__name__)


def setup_logging(role: str, level: str = "INFO") -> logging.Logger:
    """One line per record on stderr: time, role, level, message. A crash in native code (a signal such as
    SIGABRT or SIGSEGV) also leaves every thread's Python stack there."""
    with contextlib.suppress(ValueError, OSError):  # a stderr with no file behind it (captured in a test)
        faulthandler.enable()
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


class ThrottledLog:
    """A log line at most once per period; the next one says how many were suppressed. Thread-safe."""

    def __init__(self, period_s: float = LOG_PERIOD_S, clock: Callable[[], float] = time.monotonic,
                 logger: logging.Logger | None = None) -> None:
        self.period_s = period_s
        self._logger = logger or log
        self._clock = clock
        self._last = -float("inf")
        self._suppressed = 0
        self._lock = threading.Lock()

    def warning(self, message: str, *args: Any, exc_info: bool = False) -> None:
        self._log(logging.WARNING, message, *args, exc_info=exc_info)

    def info(self, message: str, *args: Any) -> None:
        self._log(logging.INFO, message, *args)

    def _log(self, level: int, message: str, *args: Any, exc_info: bool = False) -> None:
        with self._lock:
            now = self._clock()
            if now - self._last < self.period_s:
                self._suppressed += 1
                return
            suppressed, self._suppressed, self._last = self._suppressed, 0, now
        if suppressed:
            message += f" ({suppressed} similar suppressed)"
        self._logger.log(level, message, *args, exc_info=exc_info)
