"""A log as tables (CSV) and as a Foxglove viewing file with the camera frames.

Tables: ``episodes.csv`` (the EpisodeRecords of all actors), ``exploration.csv``, and
one CSV per key that carries counters (Stats, RateState, ReplayStats), named after the key below the run
(``metrics_learner_0.csv``, ``replay_stats.csv``, ``metrics_recorder_0.csv``, ...).
Every row starts with the log and publish times in seconds since the Unix epoch.

The viewing file (``--images``) holds the JSON views of ``views.py`` for every
message of the log, camera frames included: the recorder leaves frames out by
default (``recorder.images``) because encoding them costs CPU and doubles the size
of the episodes, so this offline step makes them when someone wants to watch.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

from common.wire.messages import COUNTER_TYPES, EpisodeRecord, ExplorationState
from replay.recorder.arrival import relative_key
from replay.recorder.reader import LogFile
from replay.recorder.views import ViewMaker, message_view
from replay.recorder.writer import LogWriter

TIME_COLUMNS = ("log_time", "publish_time")


@dataclass
class Tables:
    episodes: list[dict] = field(default_factory=list)
    stats: dict[str, list[dict]] = field(default_factory=dict)  # key below the run -> rows of its counters
    exploration: list[dict] = field(default_factory=list)


def collect(log: LogFile) -> Tables:
    """The metrics of a log as rows of plain values, in log-time order."""
    tables = Tables()
    root = log.keys().root
    for record, message in log.messages(EpisodeRecord, ExplorationState, *COUNTER_TYPES):
        row = {"log_time": record.log_ns / 1e9, "publish_time": record.publish_ns / 1e9}
        if isinstance(message, ExplorationState):
            view = message_view(message)
            row.update({name: value for name, value in view.items() if not isinstance(value, dict)})
            row.update({f"counters.{name}": value for name, value in view["counters"].items()})
            tables.exploration.append(row)
            continue
        row.update(message_view(message))
        if isinstance(message, COUNTER_TYPES):
            tables.stats.setdefault(relative_key(root, record.topic), []).append(row)
        else:
            tables.episodes.append(row)
    return tables


def write_csv(rows: list[dict], path: Path) -> None:
    """Columns in first-seen order; a value missing from a row is left empty."""
    columns = list(dict.fromkeys(name for row in rows for name in row))
    with open(path, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns, restval="")
        writer.writeheader()
        writer.writerows(rows)


def export_csv(log: LogFile, directory: Path) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    tables = collect(log)
    files = {"episodes.csv": tables.episodes, "exploration.csv": tables.exploration}
    files.update({f"{key.replace('/', '_')}.csv": rows for key, rows in sorted(tables.stats.items())})
    written = []
    for name, rows in files.items():
        if rows:
            write_csv(rows, directory / name)
            written.append(directory / name)
    return written


def export_images(log: LogFile, target: Path, image_format: str = "png") -> int:
    """Writes the viewing file; returns the number of view messages in it."""
    config = log.config()
    keys = log.keys()
    views = ViewMaker(keys.root, 1.0 / config.env.policy_frequency, images=True, image_format=image_format)
    writer = LogWriter(target, config, views=None)
    try:
        for record in log.records(log.wire_topics()):
            if views.wants(record.message_type):
                for view in views.views(record.topic, record.data, record.log_ns):
                    writer.write_view(view)
    finally:
        writer.close()
    return writer.view_messages
