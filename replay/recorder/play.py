"""Putting a log back on Zenoh: its wire messages, byte for byte, in log-time order.

At recorded speed (``speed`` 1), faster or slower, or as fast as possible (``speed``
0); optionally only some keys, and optionally into another run, so a fresh replay
service can be filled from a log and a learner trained offline on recorded
episodes. Zenoh drops a put that no subscriber matches, so playing first waits (up
to ``wait_s``) for every key to have a subscriber and reports the keys that had none.
Like the recorder, this moves raw payload bytes: the receivers check them.
"""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable

import zenoh

from common.keys import Keys
from replay.recorder.reader import LogError, LogFile

MATCH_POLL_S = 0.05


@dataclass
class PlayReport:
    published: Counter = field(default_factory=Counter)  # messages per target key
    unmatched: list[str] = field(default_factory=list)  # target keys no subscriber matched before playing
    seconds: float = 0.0


def retarget(key: str, source: Keys, target: Keys) -> str:
    """The key under the target run: d3rqn/a/episodes -> d3rqn/b/episodes."""
    prefix = source.root + "/"
    if not key.startswith(prefix):
        raise LogError(f"key {key!r} is not under the recorded run {source.root!r}")
    return f"{target.root}/{key[len(prefix):]}"


def select_topics(topics: list[str], source: Keys, patterns: list[str] | None) -> list[str]:
    """The topics matching any pattern (key expressions relative to the run: 'episodes', 'metrics/**')."""
    if not patterns:
        return list(topics)
    try:
        expressions = [zenoh.KeyExpr(f"{source.root}/{pattern}") for pattern in patterns]
    except zenoh.ZError as error:
        raise LogError(f"bad key pattern in {patterns}: {error}") from None
    return [topic for topic in topics if any(expression.intersects(zenoh.KeyExpr(topic)) for expression in expressions)]


def play(log: LogFile, session: zenoh.Session, target: Keys, patterns: list[str] | None = None,
         speed: float = 1.0, wait_s: float = 5.0, clock: Callable[[], float] = time.monotonic,
         sleep: Callable[[float], None] = time.sleep) -> PlayReport:
    if speed < 0:
        raise LogError(f"speed must be >= 0 (0: as fast as possible), got {speed}")
    source = log.keys()
    topics = select_topics(log.wire_topics(), source, patterns)
    if not topics:
        raise LogError(f"{log.path}: no recorded key matches {patterns}")
    report = PlayReport()
    publishers = {topic: session.declare_publisher(retarget(topic, source, target),
                                                   congestion_control=zenoh.CongestionControl.BLOCK)
                  for topic in topics}
    try:
        report.unmatched = _wait_for_subscribers(publishers, wait_s, clock, sleep)
        started, first_ns = clock(), None
        for record in log.records(topics):
            first_ns = record.log_ns if first_ns is None else first_ns
            if speed > 0:
                delay = started + (record.log_ns - first_ns) / 1e9 / speed - clock()
                if delay > 0:
                    sleep(delay)
            publishers[record.topic].put(record.data)
            report.published[retarget(record.topic, source, target)] += 1
        report.seconds = clock() - started
    finally:
        for publisher in publishers.values():
            publisher.undeclare()
    return report


def _wait_for_subscribers(publishers: dict, wait_s: float, clock, sleep) -> list[str]:
    deadline = clock() + wait_s
    while True:
        waiting = sorted(str(p.key_expr) for p in publishers.values() if not p.matching_status.matching)
        if not waiting or clock() >= deadline:
            return waiting
        sleep(MATCH_POLL_S)
