"""The evaluation's status line: episodes done / total, episodes/s, steps/s, elapsed time and ETA."""

from __future__ import annotations

import sys
import time
from typing import TextIO

from common.analysis.stats import EvaluationEpisode
from common.eta import clock_time

PREFIX = "evaluate: "


class EvaluationStatus:
    """One status line, silent without a stream.

    On a terminal the line is rewritten in place; otherwise one line is written per period.
    """

    def __init__(self, total: int, period_s: float, stream: TextIO | None = sys.stderr, clock=time.monotonic) -> None:
        self.total, self.period_s, self.stream, self.clock = total, period_s, stream, clock
        self.started = self.shown = clock()
        self.episodes = self.steps = 0
        self.rewrite = stream is not None and stream.isatty()

    def add(self, episode: EvaluationEpisode) -> None:
        self.episodes += 1
        self.steps += episode.length
        self.tick()

    def tick(self) -> None:
        if self.clock() - self.shown >= self.period_s:
            self.show()

    def show(self, final: bool = False) -> None:
        self.shown = self.clock()
        if self.stream is None:
            return
        line = evaluation_line(self.episodes, self.total, self.steps, self.shown - self.started)
        end = "\n" if final or not self.rewrite else ""
        self.stream.write(("\r" if self.rewrite else "") + line + end)
        self.stream.flush()


def evaluation_line(done: int, total: int, steps: int, elapsed_s: float) -> str:
    rate = done / elapsed_s if elapsed_s > 0 else 0.0
    eta = clock_time((total - done) / rate) if rate > 0 else "?"
    step_rate = steps / elapsed_s if elapsed_s > 0 else 0.0
    return (f"{PREFIX}{done}/{total} episodes ({100 * done / max(total, 1):.1f}%), {rate:.2f} episodes/s, "
            f"{step_rate:.0f} steps/s, elapsed {clock_time(elapsed_s)}, ETA {eta}")


def is_evaluation_line(line: str) -> bool:
    """Whether a line of evaluate's output is its status line (the experiment runner shows the latest)."""
    counts = line.removeprefix(PREFIX).split(" episodes (", 1)[0] if line.startswith(PREFIX) else ""
    done, _, total = counts.partition("/")
    return done.isdigit() and total.isdigit()
