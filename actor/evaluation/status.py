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

    On a terminal the line is rewritten in place every `period_s`; into a file or a pipe (a log) one line is
    written every `log_period_s`, since an evaluation beside a long run would otherwise fill its log.
    """

    def __init__(self, total: int, period_s: float, stream: TextIO | None = sys.stderr, clock=time.monotonic,
                 log_period_s: float | None = None) -> None:
        self.total, self.period_s, self.stream, self.clock = total, period_s, stream, clock
        self.started = self.shown = clock()
        self.episodes = self.steps = 0
        self.rewrite = stream is not None and stream.isatty()
        self.line_period_s = period_s if self.rewrite or log_period_s is None else max(period_s, log_period_s)

    def add(self, episode: EvaluationEpisode) -> None:
        self.episodes += 1
        self.steps += episode.length
        self.tick()

    def tick(self) -> None:
        if self.clock() - self.shown >= self.line_period_s:
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
    step_speed = steps / elapsed_s if elapsed_s > 0 else 0.0
    return (f"{PREFIX}{done}/{total} episodes ({100 * done / max(total, 1):.1f}%), {rate:.2f} episodes/s, "
            f"{step_speed:.0f} steps/s, elapsed {clock_time(elapsed_s)}, ETA {eta}")


def is_evaluation_line(line: str) -> bool:
    """Whether a line of evaluate's output is its status line (the experiment runner shows the latest)."""
    counts = line.removeprefix(PREFIX).split(" episodes (", 1)[0] if line.startswith(PREFIX) else ""
    done, _, total = counts.partition("/")
    return done.isdigit() and total.isdigit()
