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
from common.wire.messages import EpisodeRecord
from common.wire.metrics import LearnerStats
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
    learner_key = log.keys().metrics_source("learner", "0")  # older learners' learner/progress: the same source
    learner_rows = []
    for record, message in log.messages(EpisodeRecord, LearnerStats):
        if isinstance(message, EpisodeRecord):
            curves.episode_returns.append(message.episode_return)
            curves.episode_lengths.append(message.length)
            curves.episode_epsilons.append(message.epsilon)
            curves.episode_off_greedy.append(message.off_greedy)
        elif record.topic == learner_key:
            learner_rows.append(message)
    kept = [row for row in learner_rows if math.isfinite(row.loss_abs_diff)]  # NaN: no pair of updates that report
    curves.learner_updates.extend(float(row.updates) for row in kept)
    curves.loss_abs_diffs.extend(row.loss_abs_diff for row in kept)

