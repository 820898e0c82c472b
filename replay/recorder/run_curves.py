"""One run's training curves, read from its logs for the comparison's figures (common/analysis/figures.py).

``read_run_curves`` takes what the training figures need from a run's logs (a resumed run has several,
``recorder.log_segments``): the actors' EpisodeRecords in the order the recorder received them and the
learner's metrics reports.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

from common.analysis.figures import RunCurves
from common.wire.messages import EpisodeRecord, Stats
from replay.recorder.reader import LogError, LogFile


def read_run_curves(paths: Sequence[Path], label: str | None = None) -> RunCurves:
    """The curves of the logs of one run, in the given (recording) order; the config is the first log's."""
    if not paths:
        raise LogError("no log files given")
    with LogFile(paths[0]) as first:
        config = first.config()
    curves = RunCurves(label or config.run.name, config.exploration.strategy, config.replay.capacity)
    for path in paths:
        with LogFile(path) as log:
            _add_log(curves, log)
    return curves


def _add_log(curves: RunCurves, log: LogFile) -> None:
    learner_key = log.keys().metrics_source("learner", "0")  # learner/progress carries Stats of the same source
    learner_rows = []
    for record, message in log.messages(EpisodeRecord, Stats):
        if isinstance(message, EpisodeRecord):
            curves.episode_returns.append(message.episode_return)
            curves.episode_lengths.append(message.length)
            curves.episode_epsilons.append(message.epsilon)
            curves.episode_off_greedy.append(message.off_greedy)
        elif record.topic == learner_key:
            learner_rows.append(message.values)
    updates, diffs = finite_series(learner_rows, "updates", "loss_abs_diff")
    curves.learner_updates.extend(updates)
    curves.loss_abs_diffs.extend(diffs)


def finite_series(rows: list[dict], x_name: str, y_name: str) -> tuple[list[float], list[float]]:
    """(x, y) pairs of rows where both are finite numbers."""
    pairs = [(row.get(x_name), row.get(y_name)) for row in rows]
    kept = [(x, y) for x, y in pairs if _finite(x) and _finite(y)]
    return [x for x, _ in kept], [y for _, y in kept]


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
