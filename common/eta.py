"""Time left for a count to reach its total, from the count's rate, and times shown as [h:]mm:ss."""

from __future__ import annotations

import math
import time
from collections import deque


class Eta:
    """The rate of a growing count over the last `window_s` seconds (the whole time by default), and
    the time it needs at that rate to reach `total`. With `min_rises`, the window reaches back further
    where it must to hold that many rises of the count: one that grows in sparse bursts reads its rate
    over several of them, not 0 between two."""

    def __init__(self, total: float, window_s: float = math.inf, clock=time.monotonic, min_rises: int = 0) -> None:
        self.total = total
        self.window_s = window_s
        self.min_rises = min_rises
        self._clock = clock
        self._samples: deque[tuple[float, float]] = deque()

    def update(self, done: float) -> None:
        now = self._clock()
        self._samples.append((now, done))
        while (len(self._samples) > 2 and now - self._samples[1][0] >= self.window_s
               and self._rises_after_second() >= self.min_rises):
            self._samples.popleft()

    def _rises_after_second(self) -> int:
        values = [done for _, done in self._samples]
        return sum(later > earlier for earlier, later in zip(values[1:], values[2:]))

    def per_s(self) -> float | None:
        """Count per second over the window; None until time has passed between two samples."""
        if len(self._samples) < 2:
            return None
        (first_time, first), (last_time, last) = self._samples[0], self._samples[-1]
        return (last - first) / (last_time - first_time) if last_time > first_time else None

    def remaining_s(self) -> float | None:
        """Seconds to the total; None until the count has grown."""
        speed = self.per_s()
        if speed is None or speed <= 0.0:
            return None
        return max(self.total - self._samples[-1][1], 0.0) / speed

    def text(self) -> str:
        remaining = self.remaining_s()
        return "?" if remaining is None else clock_time(remaining)


def clock_time(seconds: float) -> str:
    minutes, second = divmod(int(round(seconds)), 60)
    hours, minute = divmod(minutes, 60)
    return f"{hours}:{minute:02d}:{second:02d}" if hours else f"{minute}:{second:02d}"
