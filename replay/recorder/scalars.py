"""A run's curves as named scalar series: the one mapping from messages that TensorBoard and `plot` share.

Each recorded EpisodeRecord, counters message and ExplorationState becomes points of series
named by tags, the names TensorBoard shows:

* ``episode/return``, ``episode/return_mean_100`` (the mean over the last 100
  episodes, the paper's curve), ``episode/length``, ``episode/epsilon`` (what the
  episode was acted with), ``episode/collided``, and where the actor counted them
  ``episode/off_greedy_share`` (its actions that were not argmax Q) with
  ``episode/off_greedy_share_100`` (over the last 100 such episodes' steps): one
  point per EpisodeRecord;
* ``<key>/<value>`` for every finite number of a counters message (flattened), the key taken below the
  run without ``metrics/``: ``learner/0/loss``, ``learner/0/loss_abs_diff``,
  ``learner/0/updates_per_s``, ``learner/0/epsilon``, ``replay/stats/episodes``,
  ``replay/rate/updates_due``, ``actor_stats/0/episodes_sent``, ``recorder/0/dropped``...;
* ``exploration/epsilon``, ``exploration/kappa``, ``exploration/started`` and
  ``exploration/counters/<name>`` of the learner's exploration state.

Every point carries where the run was when its message was recorded: env steps,
episodes recorded, learner updates, and the log time. A Stats that counts env steps
itself (the learner's ``env_steps``, the replay's ``env_steps_total``) is placed at
its own count. Episodes are placed at the env steps of the episodes recorded before
them and their own, lifted by how far the run's first env-step count in the log
(that of the first such Stats) was ahead of them, so that a log begun mid-run (a
restarted recorder, a resumed run's later segment) continues the run's axis; points
that need that lift wait for it (or for the end of the log).
"""

from __future__ import annotations

import dataclasses
from collections import deque
from typing import Collection, NamedTuple

from common.analysis.plotting import RETURN_WINDOW
from common.wire.codecs import Message
from common.wire.messages import COUNTER_TYPES, EpisodeRecord, ExplorationState, flat_values
from common.wire.metrics import LearnerStats
from common.wire.run_shape import stat_number
from replay.recorder.arrival import relative_key
from replay.recorder.reader import LogFile

CURVE_TYPES = (EpisodeRecord, ExplorationState, *COUNTER_TYPES)
CURVE_TYPE_NAMES = frozenset(cls.__name__ for cls in CURVE_TYPES)
ENV_STEP_VALUES = ("env_steps", "env_steps_total")  # Stats values that count the run's env steps
METRICS_PREFIX = "metrics/"
LEARNER_KEY = "metrics/learner/0"  # the learner's metrics, below the run

RETURN_MEAN_NAME = f"return_mean_{RETURN_WINDOW}"
RETURN_MEAN = f"episode/{RETURN_MEAN_NAME}"
EPSILON = "episode/epsilon"
OFF_GREEDY_MEAN_NAME = f"off_greedy_share_{RETURN_WINDOW}"
OFF_GREEDY_MEAN = f"episode/{OFF_GREEDY_MEAN_NAME}"
LOSS = "learner/0/loss"
LOSS_ABS_DIFF = "learner/0/loss_abs_diff"
UPDATES_START = "learner/0/start_env_steps"  # the env steps at which the replay served the first batch


class Point(NamedTuple):
    value: float
    env_steps: int
    episodes: int  # episodes recorded so far, this one included
    updates: int  # the learner's updates so far
    wall_s: float  # log time, seconds since the Unix epoch


class Curves:
    """Turns messages, in the order they were recorded, into (tag, point) pairs."""

    def __init__(self, run_root: str) -> None:
        self.run_root = run_root
        self.episodes = 0
        self.episode_steps = 0  # of the episodes recorded so far
        self.lift: int | None = None  # added to episode_steps once the run's env-step count is known
        self.updates = 0
        self._returns: deque[float] = deque(maxlen=RETURN_WINDOW)
        self._off_greedy: deque[tuple[int, int]] = deque(maxlen=RETURN_WINDOW)  # (off-greedy actions, steps)
        self._waiting: list[tuple[str, Point]] = []  # points that need the lift, not yet lifted

    def add(self, key: str, message: Message, log_ns: int) -> list[tuple[str, Point]]:
        """The points of one message (none for other types), and any that were waiting for the lift."""
        wall_s = log_ns / 1e9
        if isinstance(message, EpisodeRecord):
            return self._episode(message, wall_s)
        if isinstance(message, LearnerStats) and relative_key(self.run_root, key) == LEARNER_KEY:
            self.updates = message.updates
        if isinstance(message, COUNTER_TYPES):
            return self._stats(relative_key(self.run_root, key), flat_values(message), wall_s)
        if isinstance(message, ExplorationState):
            values = {"epsilon": message.epsilon, "kappa": message.kappa, "started": float(message.started),
                      **{f"counters/{name}": value for name, value in dataclasses.asdict(message.counters).items()}}
            return self._place("exploration", values, wall_s)
        return []

    def finish(self) -> list[tuple[str, Point]]:
        """The points still waiting at the end of the log, unlifted: no message counted the run's env steps."""
        if self.lift is None:
            self.lift = 0
        return self._release()

    def _episode(self, record: EpisodeRecord, wall_s: float) -> list[tuple[str, Point]]:
        self.episodes += 1
        self.episode_steps += record.length
        self._returns.append(record.episode_return)
        values = {"return": record.episode_return, RETURN_MEAN_NAME: sum(self._returns) / len(self._returns),
                  "length": record.length, "epsilon": record.epsilon, "collided": float(record.collided)}
        if record.off_greedy >= 0 and record.length > 0:
            self._off_greedy.append((record.off_greedy, record.length))
            values["off_greedy_share"] = record.off_greedy / record.length
            values[OFF_GREEDY_MEAN_NAME] = sum(off for off, _ in self._off_greedy) / sum(n for _, n in self._off_greedy)
        return self._place("episode", values, wall_s)

    def _stats(self, source: str, values: dict, wall_s: float) -> list[tuple[str, Point]]:
        own_steps = next((int(values[name]) for name in ENV_STEP_VALUES if stat_number(values, name) is not None),
                         None)
        released = []
        if own_steps is not None and self.lift is None:
            self.lift = max(0, own_steps - self.episode_steps)
            released = self._release()
        return released + self._place(source.removeprefix(METRICS_PREFIX), values, wall_s, own_steps)

    def _place(self, prefix: str, values: dict, wall_s: float, env_steps: int | None = None) -> list[tuple[str, Point]]:
        """Points of the finite numbers among values: at env_steps, or when None at the lifted episode steps."""
        steps = self.episode_steps if env_steps is None else env_steps
        points = [(f"{prefix}/{name}", Point(float(value), steps, self.episodes, self.updates, wall_s))
                  for name, value in values.items() if stat_number(values, name) is not None]
        if env_steps is not None:
            return points
        self._waiting.extend(points)
        return [] if self.lift is None else self._release()

    def _release(self) -> list[tuple[str, Point]]:
        waiting, self._waiting = self._waiting, []
        return [(tag, point._replace(env_steps=point.env_steps + self.lift)) for tag, point in waiting]


Series = dict[str, list[Point]]


def read_series(log: LogFile, tags: Collection[str] | None = None) -> Series:
    """The series of a log (only the given tags, if any), in log-time order."""
    curves = Curves(log.keys().root)
    series: Series = {}

    def keep(points: list[tuple[str, Point]]) -> None:
        for tag, point in points:
            if tags is None or tag in tags:
                series.setdefault(tag, []).append(point)

    for record, message in log.messages(*CURVE_TYPES):
        keep(curves.add(record.topic, message, record.log_ns))
    keep(curves.finish())
    return series
