"""The local stack's view of its run (deploy/launcher/stack.py): the system's metrics from Zenoh, rendered as the live
line, the status file and the run's summary."""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections import deque

from common.config import Config
from common.disk_space import size_text
from common.eta import Eta
from common.pacing import updates_paid_for
from common.run_dir import RunStatus
from common.wire.messages import EpisodeRecord, ReplayStats
from common.wire.metrics import LearnerStats

ETA_WINDOW_S = 300.0  # the ETA follows the rate of the last five minutes
# The line's steps/s: over a minute, or the last few episodes' arrivals where they are sparser (2,000-step
# episodes of a paced run arrive about once a minute, and a minute often holds none).
STEP_SPEED_WINDOW_S, STEP_SPEED_ARRIVALS = 60.0, 4
# What the line and the summary show before the learner's first metrics: no updates, every action exploring.
NO_LEARNER = LearnerStats(time=0.0, updates=0, env_steps=0, loss=math.nan, epsilon=1.0, updates_per_s=0.0,
                          data_wait_share=0.0, weights_version=-1)


class StackMonitor:
    """Collects the system's metrics from Zenoh and renders the live line and the status."""

    def __init__(self, total_env_steps: int = 0, clock=time.monotonic) -> None:
        self._lock = threading.Lock()
        self.returns: deque[float] = deque(maxlen=100)
        self.episodes = 0
        self.replay: ReplayStats | None = None  # the replay's last stats
        self.learner: LearnerStats | None = None  # the learner's last metrics
        self.learner_final = threading.Event()  # the learner's last metrics, sent as it stops
        self.total_env_steps = total_env_steps  # the budget; 0: not shown
        # A paced run ends when the learner has made the updates the budget owes: its ETA follows the update
        # rate once updates start, and is unknown before (the random phase runs many times faster than the
        # learner will). An unpaced run's (the replay's rate limiter says which) follows the env-step rate.
        self.eta: Eta | None = None
        self.env_step_speed = Eta(total_env_steps, STEP_SPEED_WINDOW_S, clock, STEP_SPEED_ARRIVALS)
        self._clock = clock
        self._started = clock()

    def on_metric(self, message, key: str) -> None:
        """Episode records and the learner's metrics (checked on decode); anything else on metrics/** is not
        for the line."""
        with self._lock:
            if isinstance(message, EpisodeRecord):
                self.episodes += 1
                self.returns.append(message.episode_return)
            elif isinstance(message, LearnerStats) and key.endswith("/metrics/learner/0"):
                self.learner = message
                if message.final:
                    self.learner_final.set()
                self._follow_updates()

    def on_replay_stats(self, message, key: str) -> None:
        if isinstance(message, ReplayStats):
            with self._lock:
                self.replay = message
                self.env_step_speed.update(message.env_steps_total)
                if message.rate.unpaced:
                    self.eta = self.eta or Eta(self.total_env_steps, ETA_WINDOW_S, self._clock)
                    self.eta.update(message.env_steps_total)
                self._follow_updates()

    def _follow_updates(self) -> None:
        """A paced run's ETA: the updates owed from the limiter's start mark to the budget, at its ratio and
        the recent update rate."""
        rate = self.replay.rate if self.replay is not None else None
        if rate is None or rate.unpaced or rate.start_env_steps is None or self.learner is None:
            return
        updates = self.learner.updates
        if self.eta is None:
            start = rate.start_env_steps
            owed = updates_paid_for(max(self.total_env_steps, start), start, rate.env_steps_per_update_target)
            self.eta = Eta(owed, ETA_WINDOW_S, self._clock)
        self.eta.update(updates)

    def line(self, restarts: int = 0, disk_free: int | None = None) -> str:
        with self._lock:
            mean_return = self._mean_return()
            learner = self.learner or NO_LEARNER
            elapsed = self._clock() - self._started
            env_steps = self._replay_count("env_steps_total")
            budget = (f"/{self.total_env_steps:,d} ({100 * env_steps / self.total_env_steps:5.1f}%, "
                      f"ETA {self._eta_text()})" if self.total_env_steps else "")
            return (f"[{elapsed:7.0f}s] env steps {env_steps:>9,d}{budget} | "
                    f"episodes {self.episodes:>6,d} | "
                    f"updates {learner.updates:>7,d} | "
                    f"eps {learner.epsilon:.3f} {_temperature(learner.kappa)} | "
                    f"return(100) {math.nan if mean_return is None else mean_return:8.2f} | "
                    f"upd/s {learner.updates_per_s:5.2f} | "
                    f"steps/s {self.env_step_speed.per_s() or 0.0:6.1f} | "
                    f"steps/upd {_or_nan(learner.env_steps_per_update):5.2f} | "
                    f"restarts {restarts}" + ("" if disk_free is None else f" | disk free {size_text(disk_free)}"))

    def status(self, phase: str, restarts: dict[str, int], pids: dict[str, int],
               disk_free: int | None = None) -> RunStatus:
        with self._lock:
            return RunStatus(phase=phase, env_steps=self._replay_count("env_steps_total"),
                             total_env_steps=self.total_env_steps, updates=(self.learner or NO_LEARNER).updates,
                             episodes=self.episodes, mean_return=self._mean_return(),
                             eta_s=self.eta.remaining_s() if self.eta else None,
                             elapsed_s=self._clock() - self._started,
                             restarts=dict(restarts), pids=dict(pids), disk_free_bytes=disk_free, time=time.time())

    def _replay_count(self, name: str) -> int:
        return getattr(self.replay, name) if self.replay is not None else 0

    def _eta_text(self) -> str:
        return self.eta.text() if self.eta is not None else "?"

    def _mean_return(self) -> float | None:
        return sum(self.returns) / len(self.returns) if self.returns else None

    def summary(self, config: Config, restarts: dict[str, int] | None = None, finished: bool = False) -> dict:
        """The run's figures from the learner's last metrics (and the replay's last stats); `finished`: the
        learner exited by itself, its budget paid for (a stop by hand also sends its final metrics)."""
        with self._lock:
            learner = self.learner
            replay_steps, replay_episodes = self._replay_count("env_steps_total"), self._replay_count("inserted")
            fill = dataclasses.asdict(self.replay.fill) if self.replay is not None else None
        stated = learner or NO_LEARNER
        return {
            "run": config.run.name,
            "strategy": config.exploration.strategy,
            "learner_finished": finished,
            "updates": stated.updates,
            "env_steps": stated.env_steps,
            "start_env_steps": stated.start_env_steps,
            "env_steps_per_update": stated.env_steps_per_update,  # achieved, since the start mark
            "env_steps_per_update_configured": config.pace.env_steps_per_update,
            "replay_env_steps_total": replay_steps,
            # the replay's counters come back with its snapshot, so they count the episodes of a resumed
            # run's earlier stacks too; "episodes" counts only what this stack saw
            "replay_episodes_total": replay_episodes,
            # when the buffer first filled, and the random phase's share of what it held and served
            # (replay/buffer_fill.py); None before the replay's first stats
            "replay_capacity": config.replay.capacity,
            "replay_fill": fill,
            "episodes": self.episodes,
            "restarts": dict(restarts or {}),
            # what the learner's updates ran, from its own metrics (learner.precision and update_path "auto"
            # resolve at its first batch); None before any metrics came
            "learner_precision": stated.precision or None,
            "learner_update_path": stated.update_path or None,
        }


def _or_nan(value: float | None) -> float:
    return math.nan if value is None else value


def _temperature(kappa: float) -> str:
    """kappa of the exploring actions, or "uniform": softmax explores with eps 1 at every step, so eps alone misleads."""
    return f"kappa {kappa:7.3g}" if kappa > 0 else "uniform      "
