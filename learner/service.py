"""The learner service: the learner's state and its doors; it trains on the replay's trace batches and makes
the weights and exploration state it broadcasts. Its process (session, threads, the loop) is learner/process.py.

Top to bottom, one loop: take a prefetched batch, update, feed the exploration
strategy, broadcast what changed, checkpoint now and then, and keep the policy
for the greedy learning curve (learner.keep_every, learner/keep.py). The pacing is not
here: the replay's rate limiter (replay/rate_limiter.py) answers the first
batch request the moment updates start and holds replies back while the
learner is ahead of one update per `pace.env_steps_per_update` env steps.
The learner only counts, from the replay's numbers, the achieved ratio and
when the step budget is paid for.

What it takes is checked: a batch must be what was asked for and fit the run
(frame shape, every frame it uses decompressed, actions inside the action space,
rewards within replay.reward_limit), the replay's numbers must be there, finite
and plausible (no more env steps than the budget plus a full buffer of
full-length episodes). A refused batch or message is counted by kind
(``rejected_<kind>`` in the learner's metrics) and logged at a bounded rate; an
update that fails anyway is dropped and counted (``failed_updates``), and the
learner goes on with the next batch, unless MAX_FAILED_IN_A_ROW fail in a row
(a fault of the learner, not of one batch).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from pathlib import Path

import torch

from common.checkpoint import Checkpoint
from common.cpu_capability import cpu_label
from common.disk_space import RetriedWrites
from common.config import Config
from common.config_values import to_dict
from common.eta import clock_time
from common.exploration.build import make_strategy
from common.pacing import achieved_ratio, env_steps_ceiling
from common.rejections import Rejections
from common.run_dir import RunDir
from common.wire.errors import WireError
from common.wire.messages import RateState, ReplayStats, TraceBatch, Weights, WeightsPiece, WeightsPieceAsk
from common.wire.run_shape import RunShape, check_trace_batch
from learner.feed import feed_strategy
from learner.keep import PolicyKeeper, policies_now
from learner.trace_batch import TraceArrays, TraceTensors
from learner.update import DoubleQLearner, UpdateResult
from learner.weights_shelf import WeightsShelf

log = logging.getLogger("learner")

SAMPLE_TIMEOUT_S = 30.0
IDLE_POLL_S = 0.05
WAIT_LOG_S = 10.0
MAX_FAILED_IN_A_ROW = 20  # updates that raise on consecutive batches: the learner itself is at fault; it stops
CPU_LABEL = cpu_label()


def trained_on(device: torch.device) -> str:
    """Where a kept policy says it trained (its wall time is this machine's): the CPU, and before it the GPU
    where the learner runs on one."""
    return f"{torch.cuda.get_device_name(device)}, {CPU_LABEL}" if device.type == "cuda" else CPU_LABEL


class RunClock:
    """The run's env steps, start mark and end as the replay's rate limiter states them (RateState), and
    the run's wall time.

    The limiter is the one authority on the pace: the learner re-derives nothing. Reports arrive from
    batches and two replay keys, not in order, so the step count only grows, and the limiter's word is
    its latest state with the most steps. The learner stops once the limiter has closed the run (budget
    spent, every update it pays for served, no more episodes taken: replay/rate_limiter.py) and the
    learner has made the updates the limiter says are due (an unpaced run: none more). The wall time is
    this learner session's plus that of the sessions before a resume, so that a resumed run's greedy
    curve (kept policies) carries on where it stopped.
    """

    def __init__(self, wall_clock=time.monotonic) -> None:
        self.env_steps = 0  # env steps of the whole system, as the replay last reported them
        self.start_env_steps: float | None = None  # the replay's start mark
        self.rate: RateState | None = None  # the limiter's word: its latest state with the most steps
        self.earlier_wall_s = 0.0  # the run's wall time before this session (a resumed run's checkpoint)
        self._wall_clock = wall_clock
        self._session_start = wall_clock()

    def wall_s(self) -> float:
        return self.earlier_wall_s + self._wall_clock() - self._session_start

    def observe(self, env_steps: int) -> None:
        """A batch's count of the env steps."""
        self.env_steps = max(self.env_steps, int(env_steps))

    def observe_rate(self, rate: RateState) -> None:
        if self.rate is None or rate.env_steps >= self.rate.env_steps:
            self.rate = rate
        self.observe(rate.env_steps)
        if rate.start_env_steps is not None:
            self.start_env_steps = float(rate.start_env_steps)

    def updates_due(self) -> float | None:
        """What the limiter last said the steps since its start mark pay for; None before it said."""
        return None if self.rate is None else self.rate.updates_due

    @property
    def closed(self) -> bool:
        return self.rate is not None and self.rate.closed

    def env_steps_per_update_achieved(self, updates: int) -> float:
        return achieved_ratio(self.env_steps, self.start_env_steps, updates)

    def finished(self, updates: int) -> bool:
        """The limiter has closed the run and the learner has made every update it says is due."""
        rate = self.rate
        return rate is not None and rate.closed and (rate.unpaced or updates >= rate.updates_due)

    def state_dict(self) -> dict:
        # Checkpoint.env_steps reads "env_steps": the grid runner and evaluate ask it how far a run got.
        return {"env_steps": self.env_steps, "start_env_steps": self.start_env_steps, "wall_s": self.wall_s()}

    def load_state_dict(self, state: dict) -> None:
        self.env_steps = int(state.get("env_steps", 0))
        self.earlier_wall_s = float(state.get("wall_s", 0.0))  # 0: a checkpoint from before it was kept
        mark = state.get("start_env_steps", state.get("steps_at_first_update"))
        self.start_env_steps = None if mark is None else float(mark)


@dataclasses.dataclass(frozen=True)
class Admitted:
    """A reply to a trace-batch request once checked: its traces (on the learner's device), or why
    it is refused."""
    batch: object
    traces: TraceArrays | TraceTensors | None
    error: WireError | None


class Cadence:
    """When the weights go out, a checkpoint is written or a policy is kept: after every `every`-th
    update (every > 0), and (period_s > 0) after the first update once period_s has passed since the
    last time, whichever comes first; but (min_period_s > 0) never sooner than min_period_s after the
    last time: a counted update that comes sooner is owed until then, so that a fast learner goes by time."""

    def __init__(self, every: int, period_s: float, clock=time.monotonic, min_period_s: float = 0.0) -> None:
        self.every = every
        self.period_s = period_s
        self.min_period_s = min_period_s
        self._clock = clock
        self._last = clock()
        self._owed = False  # a counted update came too soon after the last time: due once min_period_s passed

    def due(self, updates: int) -> bool:
        """Whether it is time after this update; a yes restarts the period."""
        now = self._clock()
        since = now - self._last
        self._owed = self._owed or (self.every > 0 and updates % self.every == 0)
        if since >= self.min_period_s and (self._owed or (self.period_s > 0 and since >= self.period_s)):
            self._last, self._owed = now, False
            return True
        return False


class LearnerService:
    """The learner's state and its loop; transport objects are handed in."""

    def __init__(self, config: Config, clock=time.monotonic) -> None:
        self.config = config
        self.learner = DoubleQLearner(config.network, config.learner)
        # On a GPU, batches are copied to the device by the prefetch threads while the previous
        # update runs (pinned buffers, a side stream); on a CPU the arrays are used where they lie.
        self.stager = self.learner.stager() if self.learner.device.type == "cuda" else None
        self.strategy = make_strategy(config.exploration, config.network.n_actions)
        self.clock = RunClock(clock)
        self.checkpoints = Cadence(config.learner.checkpoint_every, config.learner.checkpoint_every_s, clock)
        keeping = config.learner.keep_every > 0 or config.learner.keep_every_s > 0
        cadence = Cadence(config.learner.keep_every, config.learner.keep_every_s, clock) if keeping else None
        self.keeper = PolicyKeeper(RunDir.of(config), cadence, config.learner.keep_encoding)
        self.episodes_stored = 0
        self.bmc_observations = 0  # transitions passed to the strategy's on_returns
        self._resumed_env_steps: int | None = None
        self._lock = threading.Lock()
        self.latest_weights: Weights | None = None
        self.shelf = WeightsShelf(lambda: self.latest_weights)  # the latest weights in pieces, for downloads
        self.checkpoint_dir = RunDir.of(config).checkpoints
        self.checkpoint_writes = RetriedWrites("checkpoint", RunDir.of(config).checkpoint, log)
        self.shape = RunShape.of(config)
        self.rejections = Rejections(log)
        self.failed_updates = 0
        self._failed_in_a_row = 0
        self.link = None  # the HubLink: its doors count malformed messages, its sessions the reopens
        self.max_env_steps = env_steps_ceiling(config)
        self._monotonic = clock
        self._heard_at: float | None = None  # the replay's last word (stats, rate, a batch)

    @property
    def updates(self) -> int:
        return self.learner.updates

    # --- inputs from Zenoh callbacks ----------------------------------------------------

    def on_replay_stats(self, stats: ReplayStats, key: str = "") -> None:
        if not isinstance(stats, ReplayStats):
            self.rejections.reject("stats_wrong_type", f"a {type(stats).__name__} on replay/stats")
        elif self._replay_numbers(stats.rate, stats.env_steps_total, "stats"):
            with self._lock:
                self.episodes_stored = stats.episodes

    def on_replay_rate(self, rate: RateState, key: str = "") -> None:
        if not isinstance(rate, RateState):
            self.rejections.reject("rate_wrong_type", f"a {type(rate).__name__} on replay/rate")
        else:
            self._replay_numbers(rate, rate.env_steps, "rate")

    def _replay_numbers(self, rate: RateState, env_steps: int, door: str) -> bool:
        """Observes the env steps and the rate limiter's start mark and close; False (counted) if the steps
        are more than this run can have (the wire checked the rest)."""
        if env_steps > self.max_env_steps:
            self.rejections.reject(f"{door}_values", f"replay/{door}: {env_steps} env steps, more than "
                                   f"{self.max_env_steps} (budget plus a full buffer)")
            return False
        self._observe(env_steps, rate)
        return True

    def silent_s(self) -> float:
        """Seconds since the replay's last word; 0 before the first (the learner waits for one anyway)."""
        with self._lock:
            return 0.0 if self._heard_at is None else self._monotonic() - self._heard_at

    def _observe(self, env_steps: int, rate: RateState | None = None) -> None:
        with self._lock:
            self._heard_at = self._monotonic()
            resumed = self._resumed_env_steps
            if resumed is not None:
                self._resumed_env_steps = None
                if env_steps < resumed:
                    log.warning("the replay counts %d env steps, fewer than this checkpoint's %d: it was started "
                                "without --resume and lost the run's counters; the step budget now waits for "
                                "its new count", env_steps, resumed)
                    self.clock.env_steps, self.clock.rate = 0, None
            if rate is None:
                self.clock.observe(env_steps)
            else:
                self.clock.observe_rate(rate)

    def serve_latest_weights(self, request_message) -> Weights | None:
        """A query without payload gets the latest weights; one carrying a message is refused."""
        if request_message is not None:
            self.rejections.reject("weights_query", f"a query for the latest weights carrying a "
                                                    f"{type(request_message).__name__}")
            return None
        return self.latest_weights

    def serve_weights_piece(self, ask) -> WeightsPiece | None:
        """A piece of the latest weights (or of the version asked for, while the shelf holds it)."""
        if not isinstance(ask, WeightsPieceAsk):
            self.rejections.reject("weights_piece_query", f"a {type(ask).__name__} where a WeightsPieceAsk belongs")
            return None
        return self.shelf.piece(ask)

    # --- decisions ----------------------------------------------------------------------

    def finished(self) -> bool:
        """The step budget is spent and the learner has made the updates it pays for."""
        with self._lock:
            return self.clock.finished(self.updates)

    def env_steps_per_update(self) -> float:
        """The run's achieved ratio: env steps since the replay's start mark per update."""
        with self._lock:
            return self.clock.env_steps_per_update_achieved(self.updates)

    # --- the work -----------------------------------------------------------------------

    def start_updates(self) -> None:
        self.strategy.start()

    def admit(self, batch: TraceBatch) -> Admitted:
        """Checks a reply to a trace-batch request against the run and decodes its frames (in a
        prefetch thread, off the update's critical path); on a GPU, stages it on the device."""
        config = self.config.learner
        try:
            if not isinstance(batch, TraceBatch):
                raise WireError(f"a {type(batch).__name__} in reply to a trace-batch request", "wrong_type")
            check_trace_batch(batch, self.shape, config.batch_size, config.trace_length)
            if batch.env_steps_total > self.max_env_steps:
                raise WireError(f"TraceBatch: {batch.env_steps_total} env steps, more than {self.max_env_steps}",
                                "values")
            observations = batch.observations_array()
        except WireError as error:
            return Admitted(batch, None, error)
        traces = TraceArrays.from_batch(batch, observations)
        if self.stager is None:
            return Admitted(batch, traces, None)
        try:
            return Admitted(batch, self.stager.stage(traces), None)
        except ValueError as error:  # the sizes the network needs (learner.trace_batch.checked_arrays)
            return Admitted(batch, None, WireError(str(error), "shape"))

    def train_on(self, batch: TraceBatch | Admitted) -> UpdateResult | None:
        """One update on one batch (admitted already, or admitted here); feeds the strategy what it
        needs; returns the update's result, or None when the batch was refused or the update failed (counted)."""
        admitted = batch if isinstance(batch, Admitted) else self.admit(batch)
        if admitted.error is not None:
            self.rejections.reject(f"batch_{admitted.error.kind}", str(admitted.error))
            return None
        self._observe(admitted.batch.env_steps_total)
        traces = admitted.traces
        try:
            result = self.learner.update(traces, with_q_after=self.strategy.needs_q_after)
        except Exception:
            self.failed_updates += 1
            self._failed_in_a_row += 1
            if self._failed_in_a_row >= MAX_FAILED_IN_A_ROW:
                raise
            self.rejections.reject("update_failed", f"an update failed ({self.failed_updates} so far); "
                                                    f"the batch is dropped")
            log.debug("the failed update", exc_info=True)
            return None
        self._failed_in_a_row = 0
        self.bmc_observations += feed_strategy(self.strategy, result, self.clock.env_steps, self.config)
        return result

    def make_weights(self) -> Weights:
        """The online network's weights as broadcast and served, in learner.weights_encoding; whole
        (float32, logged) when a value is beyond that encoding's range."""
        tensors, encoding = self.learner.online_weights(), self.config.learner.weights_encoding
        try:
            weights = Weights.from_float32(self.updates, tensors, encoding, created=time.time())
        except WireError as error:
            if error.kind != "weights_encoding":
                raise
            log.warning("weights version %d go out as float32: %s", self.updates, error)
            weights = Weights.from_float32(self.updates, tensors, created=time.time())
        self.latest_weights = weights
        return weights

    def checkpoint(self) -> Path:
        with self._lock:
            clock = self.clock.state_dict()
        return Checkpoint(learner=self.learner.state_dict(), exploration=self.strategy.state_dict(), clock=clock,
                          config=to_dict(self.config)).save(self.checkpoint_dir)

    def try_checkpoint(self) -> Path | None:
        """A checkpoint, or None where it cannot be written (a full disk): training goes on (RetriedWrites)."""
        return self.checkpoint_writes.attempt(self.checkpoint)

    def checkpoint_if_due(self) -> None:
        if self.checkpoints.due(self.updates):
            self.try_checkpoint()

    def keep_policy(self) -> None:
        """Keeps the online weights, and the shadow kinds due beside them, with the run's updates, env steps and
        wall time (written in the background)."""
        with self._lock:
            env_steps, wall_s = self.clock.env_steps, self.clock.wall_s()
        self.keeper.keep(policies_now(self.learner, self.config, env_steps, wall_s, trained_on(self.learner.device)))

    def keep_policy_if_due(self) -> None:
        if self.keeper.due(self.updates):
            self.keep_policy()

    def keep_last_policy(self) -> None:
        """At the end: the policy the run stopped with, unless just kept; returns once every file is written."""
        if self.keeper.cadence is not None and self.keeper.last_kept != self.updates:
            self.keep_policy()
        self.keeper.wait()

    def resume(self) -> None:
        checkpoint = Checkpoint.load(self.checkpoint_dir, complete=True)
        self.learner.load_state_dict(checkpoint.learner)
        self.strategy.load_state_dict(checkpoint.exploration)
        self.clock.load_state_dict(checkpoint.clock)
        self._resumed_env_steps = self.clock.env_steps
        log.info("resumed from %s: %d updates, %d env steps, %s of wall time", self.checkpoint_dir, self.updates,
                 self.clock.env_steps, clock_time(self.clock.earlier_wall_s))
