"""The learner process: waits for the replay to fill, then trains and broadcasts.

Top to bottom, one loop: take a prefetched batch, wait if the system has not
paid for this update with environment steps, update, feed the exploration
strategy, broadcast what changed, checkpoint now and then.
"""

from __future__ import annotations

import logging
import math
import signal
import threading
import time
from pathlib import Path

import numpy as np
import torch

from common.config import Config, to_dict
from common.exploration import make_strategy
from common.logs import Every, setup_logging
from common.transport import Keys, declare_liveliness, open_session, publisher, request, serve, subscribe
from common.wire import ExplorationState, Stats, TraceBatch, Weights
from learner.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from learner.pacing import StepClock
from learner.prefetch import Prefetcher
from learner.update import DoubleQLearner, TraceBatch as Traces

log = logging.getLogger("learner")

SAMPLE_TIMEOUT_S = 30.0
IDLE_POLL_S = 0.05
CHECKPOINT_SECTIONS = ("learner", "exploration", "clock", "config")


class LearnerProcess:
    """The learner's state and its loop; transport objects are handed in."""

    def __init__(self, config: Config) -> None:
        self.config = config
        self.learner = DoubleQLearner(config.network, config.learner)
        self.strategy = make_strategy(config.exploration, config.network.n_actions)
        self.clock = StepClock()
        self.episodes_stored = 0
        self._lock = threading.Lock()
        self.latest_weights: Weights | None = None
        self.checkpoint_dir = Path(config.run.runs_dir) / config.run.name / "checkpoints"

    @property
    def updates(self) -> int:
        return self.learner.updates

    # --- inputs from Zenoh callbacks ----------------------------------------------------

    def on_replay_stats(self, stats: Stats, key: str = "") -> None:
        if isinstance(stats, Stats) and stats.source == "replay":
            self._observe(int(stats.values.get("env_steps_total", 0)), int(stats.values.get("episodes", 0)))

    def _observe(self, env_steps_total: int, episodes_stored: int) -> None:
        with self._lock:
            self.clock.observe(env_steps_total)
            self.episodes_stored = episodes_stored

    def serve_latest_weights(self, request_message) -> Weights | None:
        return self.latest_weights

    # --- decisions ----------------------------------------------------------------------

    def ready_to_start(self) -> bool:
        """The paper waits for a full buffer (999 episodes); decreasing epsilon waits for n_start steps."""
        with self._lock:
            if self.config.exploration.strategy == "decreasing":
                return self.clock.env_steps >= self.config.learner.start_steps
            return self.episodes_stored >= self.config.learner.start_episodes

    def may_update(self) -> bool:
        with self._lock:
            return self.clock.may_update(self.updates, self.config.learner.env_steps_per_update,
                                         self.config.learner.ratio_tolerance)

    def budget_spent(self) -> bool:
        with self._lock:
            return self.clock.env_steps >= self.config.learner.total_env_steps

    # --- the work -----------------------------------------------------------------------

    def start_updates(self) -> None:
        with self._lock:
            self.clock.start_updates()
        self.strategy.start()

    def train_on(self, batch: TraceBatch) -> float:
        """One update on one batch; feeds the strategy what it needs; returns the loss."""
        # The clock reads only the replay's stats: batches from parallel requests arrive out of
        # order, and an older count would look like a replay restart.
        traces = Traces(batch.observations_array(), np.array(batch.actions), np.array(batch.rewards),
                        np.array(batch.terminated))
        result = self.learner.update(traces, with_q_after=self.strategy.needs_q_after)
        self.strategy.on_env_steps(self.clock.env_steps)
        if self.strategy.needs_q_after:
            self.strategy.on_update(result.q_before, result.q_after)
        if self.strategy.needs_returns:
            self.strategy.on_returns(result.g_greedy, result.g_uniform)
        return result.loss

    def make_weights(self) -> Weights:
        self.latest_weights = Weights(version=self.updates, tensors=self.learner.online_weights(),
                                      created=time.time())
        return self.latest_weights

    def checkpoint(self) -> Path:
        with self._lock:
            clock = self.clock.state_dict()
        return save_checkpoint(self.checkpoint_dir, {
            "learner": self.learner.state_dict(),
            "exploration": self.strategy.state_dict(),
            "clock": clock,
            "config": to_dict(self.config),
        })

    def resume(self) -> None:
        payload = load_checkpoint(self.checkpoint_dir, CHECKPOINT_SECTIONS)
        self.learner.load_state_dict(payload["learner"])
        self.strategy.load_state_dict(payload["exploration"])
        self.clock.load_state_dict(payload["clock"])
        log.info("resumed from %s: %d updates, %d env steps", self.checkpoint_dir, self.updates, self.clock.env_steps)


def run_learner(config: Config, resume: bool = False) -> None:
    """Trains until the step budget is spent or SIGINT/SIGTERM; checkpoints at exit."""
    setup_logging("learner")
    if config.learner.torch_threads:
        torch.set_num_threads(config.learner.torch_threads)
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    process = LearnerProcess(config)
    if resume:
        try:
            process.resume()
        except CheckpointError as error:
            log.error("cannot resume: %s", error)
            raise SystemExit(1) from None
    log.info("device %s, strategy %s, %d torch threads", process.learner.device,
             config.exploration.strategy, torch.get_num_threads())
    keys = Keys(config.transport.namespace, config.run.name)
    session = open_session(config.transport)
    try:
        declared = [declare_liveliness(session, keys.liveliness("learner", "0")),
                    subscribe(session, keys.replay_stats, process.on_replay_stats),
                    serve(session, keys.weights_latest, process.serve_latest_weights)]
        outputs = Outputs(session, keys)
        outputs.weights(process.make_weights())
        _train(process, outputs, stop, session, keys)
        for item in declared:
            item.undeclare()
    finally:
        session.close()


class Outputs:
    """Everything the learner publishes."""

    def __init__(self, session, keys: Keys) -> None:
        self._weights = publisher(session, keys.weights)
        self._exploration = publisher(session, keys.exploration)
        self._metrics = publisher(session, keys.metrics_source("learner", "0"))
        self._progress = publisher(session, keys.learner_progress)
        self._last_exploration: dict | None = None

    def weights(self, weights: Weights) -> None:
        self._weights.put(weights)

    def exploration(self, strategy, force: bool = False) -> None:
        state = strategy.state_dict()
        if force or state != self._last_exploration:
            self._exploration.put(ExplorationState(**state))
            self._last_exploration = state

    def progress(self, process: LearnerProcess) -> None:
        with process._lock:
            due = process.clock.updates_due(process.config.learner.env_steps_per_update)
            env_steps = process.clock.env_steps
        self._progress.put(Stats(source="learner", time=time.time(),
                                 values={"updates": process.updates, "updates_due": due, "env_steps": env_steps}))

    def metrics(self, values: dict) -> None:
        self._metrics.put(Stats(source="learner", time=time.time(), values=values))


def _train(process: LearnerProcess, outputs: Outputs, stop: threading.Event, session, keys: Keys) -> None:
    config = process.config.learner
    heartbeat = Every(config.log_period_s)
    while not process.ready_to_start() and not stop.is_set():
        if heartbeat.due():
            outputs.exploration(process.strategy, force=True)  # late actors learn the state too
            log.info("waiting for the replay: %d/%d episodes, %d env steps", process.episodes_stored,
                     config.start_episodes, process.clock.env_steps)
        stop.wait(IDLE_POLL_S * 10)
    if stop.is_set():
        log.info("stopped before updates started; checkpoint %s", process.checkpoint())
        return
    if process.updates == 0:
        process.start_updates()
    else:
        process.strategy.start()
    outputs.exploration(process.strategy, force=True)
    log.info("updates start at %d env steps with %d episodes stored", process.clock.env_steps,
             process.episodes_stored)

    prefetcher = Prefetcher(lambda message: request(session, keys.replay_sample, message, SAMPLE_TIMEOUT_S),
                            config.batch_size, config.trace_length, config.prefetch)
    report = Report(process, prefetcher)
    try:
        while not stop.is_set() and not process.budget_spent():
            if not process.may_update():
                report.pace_wait(stop)
                continue
            batch = prefetcher.next(stop)
            if batch is None:
                break
            report.loss(process.train_on(batch))
            outputs.progress(process)
            outputs.exploration(process.strategy)
            if process.updates % config.weights_every == 0:
                outputs.weights(process.make_weights())
            if process.updates % config.checkpoint_every == 0:
                process.checkpoint()
            if heartbeat.due():
                outputs.metrics(report.values())
    finally:
        prefetcher.close()
        outputs.weights(process.make_weights())
        path = process.checkpoint()
        outputs.metrics(report.values())
        log.info("stopped after %d updates, %d env steps; checkpoint %s", process.updates,
                 process.clock.env_steps, path)


class Report:
    """Running figures for the learner's log line and metrics message."""

    def __init__(self, process: LearnerProcess, prefetcher: Prefetcher) -> None:
        self.process = process
        self.prefetcher = prefetcher
        self.started = time.monotonic()
        self.pace_wait_s = 0.0
        self.losses: list[float] = []
        self.loss_diffs: list[float] = []
        self._previous_loss: float | None = None
        self._window_start = (time.monotonic(), process.updates, 0.0)

    def loss(self, value: float) -> None:
        if not math.isfinite(value):
            log.warning("non-finite loss %s at update %d", value, self.process.updates)
        if self._previous_loss is not None:
            self.loss_diffs.append(abs(value - self._previous_loss))
        self._previous_loss = value
        self.losses.append(value)

    def pace_wait(self, stop: threading.Event) -> None:
        started = time.monotonic()
        stop.wait(IDLE_POLL_S)
        self.pace_wait_s += time.monotonic() - started

    def values(self) -> dict:
        now = time.monotonic()
        window_time, window_updates, window_data_wait = self._window_start
        elapsed = max(now - window_time, 1e-9)
        updates = self.process.updates
        strategy = self.process.strategy
        values = {
            "updates": updates,
            "env_steps": self.process.clock.env_steps,
            "loss": float(np.mean(self.losses)) if self.losses else float("nan"),
            # the paper's training figure: |loss_k - loss_k-1| of consecutive updates, averaged here
            "loss_abs_diff": float(np.mean(self.loss_diffs)) if self.loss_diffs else float("nan"),
            "epsilon": float(strategy.epsilon),
            "updates_per_s": (updates - window_updates) / elapsed,
            "data_wait_share": (self.prefetcher.wait_s - window_data_wait) / elapsed,
            "pace_wait_s": self.pace_wait_s,
            "weights_version": self.process.latest_weights.version if self.process.latest_weights else -1,
        }
        log.info("updates %(updates)d, env steps %(env_steps)d, loss %(loss).5f, epsilon %(epsilon).3f, "
                 "%(updates_per_s).2f updates/s, waiting for data %(data_wait_share).0f%% of the time, "
                 "paced %(pace_wait_s).1fs in total", {**values, "data_wait_share": 100 * values["data_wait_share"]})
        self.losses.clear()
        self.loss_diffs.clear()
        self._window_start = (now, updates, self.prefetcher.wait_s)
        return values
