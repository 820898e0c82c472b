"""The replay service: episodes in over Zenoh, trace batches out on a queryable, stats out.

It owns the system's one rate limiter (replay/rate_limiter.py): it counts every
env step received and every trace batch served, holds a batch request back while
the learner is ahead, and publishes on ``replay/rate`` whether the actors must
hold their next episode (the learner is behind, or the run's budget is spent).

Zenoh delivers on its own threads, which only park what arrives: every touch of
the store and the limiter holds one lock, and held requests are answered by the
service's reply threads.

Nothing is taken on trust. An episode is stored only if it fits the run
(common.wire.run_shape.check_episode: frame shape, every frame decompressed, actions inside
the action space, rewards finite and within replay.reward_limit, no longer than
env.max_steps) and was not taken before (replay/ledger.py); a request only if it
asks for what the replay serves, and while fewer than MAX_PENDING requests are
held; an exploration state only if it describes a strategy completely. What is
refused is counted by kind (``rejected_<door>_<fault>`` in the stats) and logged at
a bounded rate; nothing stored is lost because of it.

Every replay.snapshot_period_s the episodes new since the last snapshot and the
counters go to <run>/replay/snapshot/ (replay/snapshot.py), outside the lock;
``replay --resume`` restores them. Each actor hears, on ``replay/acks/<actor id>``, which of its
episodes were received, kept (in a snapshot) or refused (replay/acks.py), and sends again
what was not kept.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

from common.config import Config
from common.exploration.names import starts_by_steps
from common.logs import Every, ThrottledLog
from common.pacing import learner_stock, rate_limit_from_config, updates_ceiling
from common.rejections import Rejections
from common.run_dir import RunDir
from common.wire.state_rows import stored_units
from common.transport import PendingQuery
from common.wire.errors import WireError
from common.wire.messages import Episode, ExplorationState, ReplayStats, TraceBatchRequest
from common.wire.run_shape import RunShape, check_episode
from replay.acks import AckBook
from replay.ledger import EpisodeLedger
from replay.hold_guard import HoldGuard
from replay.memory_budget import MEGABYTE, report_budget
from replay.request_admission import log_recounted, request_fault
from replay.rate_limiter import RateLimiter, furthest_sound_counters
from replay.snapshot import Restored, SnapshotError, Snapshotter, SnapshotView
from replay.store import EpisodeStore

log = logging.getLogger("replay")

HOLD_MAX_S = 10.0  # a held request is dropped after this (the learner asks again); below its 30 s timeout
WAKE_S = 0.1  # reply threads look at expiries and the rate message at least this often
MEASURE_AFTER_FRAMES = 1_000  # the budget check is repeated once with the measured frame size
MAX_PENDING = 32  # held trace-batch requests; beyond, a request is refused at once (the learner keeps 2)


class ReplayService:
    """The store and the rate limiter behind one lock, the held requests, and the counters the stats report."""

    def __init__(self, config: Config) -> None:
        self.config = config
        self.store = EpisodeStore(capacity=config.replay.capacity,
                                  budget_bytes=int(config.replay.memory_budget_mb * MEGABYTE),
                                  trace_length=config.learner.trace_length, seed=config.replay.seed,
                                  state_units=stored_units(config), by_steps=config.replay.sample_by_steps)
        self.limiter = RateLimiter(rate_limit_from_config(config))
        self.max_trace_batch = config.replay.max_batch_size
        self.learner_stock = learner_stock(config.learner.prefetch)
        self.max_learner_updates = updates_ceiling(config)
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._pending: deque[PendingQuery] = deque()
        self.traces_served = 0
        self.rejected_requests = self.expired_requests = self.failed_samples = 0
        self.learner_rule: tuple[str, bool] | None = None  # the learner's strategy and start rule, as last stated
        self._measured = False
        self._warn_budget = ThrottledLog(60.0, logger=log)
        self._announced: tuple[str, int, bool] | None = None  # hold reason, env steps, closed: last on replay/rate
        self.shape = RunShape.of(config)
        self.ledger = EpisodeLedger()
        self.hold_guard = HoldGuard.of(config)  # episodes begun while the actors were told to hold: refused
        self.rejections = Rejections(log)
        self.snapshotter = Snapshotter(RunDir.of(config).replay_snapshot)  # in the run folder
        self.acks = AckBook(durable_on_receipt=config.replay.snapshot_period_s <= 0)
        self._snapshot_lock = threading.Lock()  # one snapshot at a time
        self.snapshot_stats: dict[str, int | float] = {"snapshots_written": 0, "snapshot_failures": 0,
                                                       "snapshot_pause_max_ms": 0.0}
        self.snapshot_taken: float | None = None  # time.time() of the last snapshot's view
        self.restored_episodes = self.restore_skipped = 0
        self.late_episodes = 0  # arrived after the run closed: not taken (replay/rate_limiter.py)
        self.late_env_steps = 0
        self._warn_late = ThrottledLog(60.0, logger=log)

    # --- inputs from Zenoh callbacks (never wait) ----------------------------------------

    def on_episode(self, episode: Episode, key: str = "") -> None:
        if not isinstance(episode, Episode):
            self.rejections.reject("episode_wrong_type", f"a {type(episode).__name__} on {key or 'episodes'}")
            return
        try:  # outside the lock: decompressing every frame takes a while
            check_episode(episode, self.shape)
        except WireError as error:
            self.rejections.reject(f"episode_{error.kind}", f"episode {episode.episode_index} of actor "
                                                            f"{episode.actor_id}: {error}")
            self.acks.refused(episode.actor_id, episode.incarnation, episode.episode_index)
            return
        name = (episode.actor_id, episode.incarnation, episode.episode_index)
        with self._lock:
            closed = self.limiter.closed
            begun_held = not closed and self._begun_while_held_locked(name, episode.in_hand)
            admitted = not closed and not begun_held and self.ledger.admit(*name)
            if admitted:
                self._store_locked(episode)
                self.acks.taken(*name)  # under the lock: a snapshot view taken after it holds the episode
            elif closed:
                self.late_episodes += 1
                self.late_env_steps += len(episode.actions)
                self.acks.refused(*name)
            elif begun_held:
                self.acks.refused(*name)
            else:
                self.acks.duplicate(*name)
        if begun_held:
            self.rejections.reject("episode_begun_while_held", f"episode {episode.episode_index} of actor "
                                   f"{episode.actor_id}: the actors have been told to hold for over "
                                   f"{self.hold_guard.grace_s:g} s and it is past what the actor had in hand "
                                   "(does it hear replay/rate?)")
        elif closed:
            self._warn_late.info("the run is closed (budget spent and paid for): episode %d of actor %d, %d steps, "
                                 "not taken (%d such so far)", episode.episode_index, episode.actor_id,
                                 len(episode.actions), self.late_episodes)
        elif not admitted:
            self.rejections.reject("episode_duplicate", f"episode {episode.episode_index} of actor "
                                   f"{episode.actor_id} (incarnation {episode.incarnation:x}) was stored before")

    def _begun_while_held_locked(self, name: tuple[int, int, int], in_hand: int) -> bool:
        """Whether the hold guard refuses the episode; one refused is noted in the ledger (no gap), not stored."""
        self.hold_guard.note_hold(bool(self.limiter.hold_reason()))
        if self.hold_guard.admits(*name, self.ledger.highest(*name[:2]), in_hand):
            return False
        self.ledger.admit(*name)
        return True

    def _store_locked(self, episode: Episode) -> None:
        store, limiter = self.store, self.limiter
        budget_evictions, started, refilling = store.evicted_for_budget, limiter.started, limiter.refilling
        store.add(episode)
        limiter.on_episode(len(episode.actions), len(store))
        if limiter.started and not started:
            log.info("updates start: %d episodes stored, %d env steps (rule: %s)", len(store),
                     limiter.env_steps, f"{limiter.limit.start_steps} steps" if limiter.limit.start_by_steps
                     else f"{limiter.limit.start_episodes} episodes")
        elif refilling and not limiter.refilling:
            log.info("refilled: %d episodes stored; updates go on after %d env steps of refill, not owed",
                     len(store), limiter.refill_env_steps)
        self._check_measured_budget()
        if store.evicted_for_budget > budget_evictions:
            self._warn_budget.warning(
                "MEMORY BUDGET IS EVICTING: the replay holds %d episodes, fewer than replay.capacity %d, "
                "because replay.memory_budget_mb %.0f is full; raise it to keep the configured buffer",
                len(store), store.capacity, self.config.replay.memory_budget_mb)
        self._changed.notify_all()

    def on_sample_request(self, pending: PendingQuery) -> None:
        """Parks a trace-batch request; a reply thread answers it when the rate limiter allows."""
        request = pending.request
        fault = self._request_fault(request)
        if fault is None and request.learner_updates >= 0:
            self._learner_updates(request)
        if fault is None:
            with self._lock:
                if len(self._pending) < MAX_PENDING:
                    self._pending.append(pending)
                    self._changed.notify_all()
                    return
            fault = ("request_overflow", f"{MAX_PENDING} requests are held already")
        with self._lock:
            self.rejected_requests += 1
        kind, text = fault
        self.rejections.reject(kind, text)
        pending.reply_error(f"rejected: {text}")

    def _learner_updates(self, request: TraceBatchRequest) -> None:
        """The updates a request states: a learner's start re-owes what it lost; a running learner's count
        above this replay's (counters lost in its restart) is counted served, and one further below it than
        the learner can hold re-owes the replies it never received."""
        updates, lost, gained, unreceived = request.learner_updates, 0, 0, 0
        with self._lock:
            if request.request_id == 0:
                lost = self.limiter.on_learner_start(updates)
            else:
                gained, unreceived = self.limiter.on_learner_updates(updates, self.learner_stock)
        log_recounted(updates, lost, gained, unreceived, self.learner_stock)

    def _request_fault(self, request) -> tuple[str, str] | None:
        return request_fault(request, self.store.trace_length, self.max_trace_batch, self.max_learner_updates)

    def on_exploration(self, state: ExplorationState, key: str = "") -> None:
        """The learner states its start rule with its exploration state; the state of a learner that
        predates that field gives it by its strategy's name (decreasing epsilon starts by steps), and is
        refused if no strategy has that name."""
        if not isinstance(state, ExplorationState):
            self.rejections.reject("exploration_wrong_type", f"a {type(state).__name__} on {key or 'exploration'}")
            return
        by_steps = state.start_by_steps
        if by_steps is None:
            try:
                by_steps = starts_by_steps(state.strategy, self.config.pace.start_by)
            except ValueError as error:
                self.rejections.reject("exploration_invalid", str(error))
                return
        with self._lock:
            if (state.strategy, by_steps) == self.learner_rule:
                return
            self.learner_rule = (state.strategy, by_steps)
            changed = by_steps != self.limiter.limit.start_by_steps
            accepted = self.limiter.set_start_by_steps(by_steps)
        if changed and accepted:
            log.info("the learner (strategy %s) starts updates at %s", state.strategy,
                     f"{self.config.pace.start_steps} env steps" if by_steps
                     else f"{self.config.pace.start_episodes} episodes")
        elif not accepted:
            log.warning("the learner (strategy %s) starts updates by %s, but they already started by the other "
                        "rule", state.strategy, "env steps" if by_steps else "episodes")

    # --- the reply threads ---------------------------------------------------------------

    def serve_pending(self, stop: threading.Event, announce=None) -> None:
        """Answers held requests while the limiter allows; calls announce(RateState) when the actors'
        hold changes and at least every stats period. Runs until stop is set; an error is logged
        and the thread goes on."""
        every = Every(self.config.replay.stats_period_s)
        warn = ThrottledLog(logger=log)
        while not stop.is_set():
            try:
                self._serve_round(every, announce)
            except Exception:  # a reply thread that died would stop the learner for good
                warn.warning("a reply thread failed; it goes on", exc_info=True)
                stop.wait(WAKE_S)

    def _serve_round(self, every: Every, announce) -> None:
        """One pass: expire, serve one held request if allowed, announce a changed hold."""
        with self._changed:
            expired = self._expire_locked()
            served = self._serve_one_locked()
            announce_now = False
            if announce is not None:
                # a change of the hold; past the budget every new step and the close too (the learner pays
                # the last steps and stops once the run is closed)
                reason = self.limiter.hold_reason()
                self.hold_guard.note_hold(bool(reason))
                now = (reason, self.limiter.env_steps if reason == "budget" else 0, self.limiter.closed)
                announce_now = now != self._announced or every.due()
                if announce_now:
                    self._announced = now
                    state = self.limiter.state(time.time())
            if served is None and not announce_now and not expired:
                self._changed.wait(WAKE_S)
        for pending in expired:
            pending.drop()
        if announce_now:  # first: the actors' release is what the learner waits for next
            announce(state)
        if served is not None:
            pending, batch = served
            if not pending.reply(batch):
                log.warning("a trace batch could not be delivered (request %d)", batch.request_id)

    def _serve_one_locked(self):
        if not (self._pending and len(self.store) and self.limiter.may_serve()):
            return None
        pending = self._pending.popleft()
        request = pending.request
        try:
            batch = self.store.sample(request.batch_size, request.request_id)
        except Exception as error:  # dropped and counted; the next request is served as usual
            self.failed_samples += 1
            pending.reply_error(f"sampling failed: {type(error).__name__}: {error}")
            raise
        self.limiter.on_served()
        self.traces_served += request.batch_size
        self._changed.notify_all()  # the announcing thread: the actors may go on now
        return pending, batch

    def _expire_locked(self) -> list[PendingQuery]:
        deadline = time.monotonic() - HOLD_MAX_S
        expired = []
        while self._pending and self._pending[0].received < deadline:
            expired.append(self._pending.popleft())
        self.expired_requests += len(expired)
        return expired

    def drop_pending(self) -> None:
        with self._lock:
            pending, self._pending = list(self._pending), deque()
        for query in pending:
            query.drop()

    # --- memory budget -------------------------------------------------------------------

    def budget_report(self, frame_bytes: float, source: str) -> bool:
        """Logs how many full-length episodes the budget holds; a loud warning if fewer than capacity."""
        return report_budget(self.config, self.store, frame_bytes, source)

    def _check_measured_budget(self) -> None:
        if not self._measured and self.store.frames >= MEASURE_AFTER_FRAMES:
            self._measured = True
            self.budget_report(self.store.frame_bytes_mean, f"measured over {self.store.frames} frames")

    # --- counters ------------------------------------------------------------------------

    def stats(self, rejected: dict[str, int] | None = None, speeds: dict | None = None) -> ReplayStats:
        """The replay/stats message; `rejected` adds the counts of messages refused before the service saw
        them, `speeds` the counters' recent rates."""
        now = time.time()
        with self._lock:
            store = self.store
            stats = ReplayStats(
                time=now, episodes=len(store), frames=store.frames, bytes=store.bytes,
                env_steps_total=store.env_steps_total, inserted=store.inserted, evicted=store.evicted,
                evicted_for_budget=store.evicted_for_budget, short_dropped=store.short_dropped,
                traces_served=self.traces_served, pending_requests=len(self._pending),
                rejected_requests=self.rejected_requests, expired_requests=self.expired_requests,
                failed_samples=self.failed_samples, episodes_missing=self.ledger.missing,
                episode_sources=self.ledger.sources, restored_episodes=self.restored_episodes,
                restore_skipped=self.restore_skipped, late_episodes=self.late_episodes,
                late_env_steps=self.late_env_steps,
                snapshot_age_s=None if self.snapshot_taken is None else now - self.snapshot_taken,
                frame_bytes_mean=store.frame_bytes_mean if store.frames else None,
                rate=self.limiter.state(now), snapshot=dict(self.snapshot_stats),
                rejected={**self.rejections.values(), **(rejected or {})}, speeds=dict(speeds or {}),
                fill=store.fill.state())
        return stats

    def limiter_state(self) -> dict:
        with self._lock:
            return self.limiter.state_dict()

    def load_limiter_state(self, state: dict) -> None:
        """Counters of this run's earlier replay, for the episodes the store holds now."""
        with self._lock:
            self.limiter.load_state_dict(state, len(self.store))
            self.store.env_steps_total = self.limiter.env_steps

    # --- the snapshot --------------------------------------------------------------------

    def write_snapshot(self) -> bool:
        """Writes the episodes new since the last snapshot and the counters; the lock is held only
        to take the view. False (logged, counted) if the snapshot could not be written."""
        with self._snapshot_lock:
            paused = time.perf_counter()
            with self._lock:
                view = SnapshotView(self.store.episodes(), self.store.counters(), self.limiter.state_dict(),
                                    self.ledger.state_dict())
                token = self.acks.view_taken()
            pause_ms = (time.perf_counter() - paused) * 1000
            try:
                report = self.snapshotter.write(view)
            except SnapshotError as error:
                self.acks.view_failed(token)
                with self._lock:
                    self.snapshot_stats["snapshot_failures"] += 1
                self._warn_budget.warning("snapshot failed: %s", error)
                return False
            self.acks.view_written(token)
            with self._lock:
                self.snapshot_taken = view.taken
                stats = self.snapshot_stats
                stats.update(snapshots_written=stats["snapshots_written"] + 1, snapshot_episodes=report.episodes,
                             snapshot_bytes=report.total_bytes, snapshot_written_bytes=report.written_bytes,
                             snapshot_written_episodes=report.written_episodes, snapshot_seconds=report.seconds,
                             snapshot_pause_ms=pause_ms,
                             snapshot_pause_max_ms=max(stats["snapshot_pause_max_ms"], pause_ms))
            return True

    def restore(self, restored: Restored, counters: dict | None) -> str:
        """Takes a snapshot's episodes and counters into the empty store. The rate limiter's counters
        come from `counters` (rate_limiter.json, saved every stats period) when they are sound and at
        least as far on as the snapshot's, else from the snapshot. Returns which were used; ValueError
        (nothing changed) if the snapshot's counters are not sound."""
        ledger = EpisodeLedger()
        ledger.load_state_dict(restored.ledger)
        state, source = furthest_sound_counters(self.limiter.limit, counters, restored.limiter)
        with self._lock:
            self.store.restore(restored.episodes, restored.store)
            self.ledger = ledger
            self.limiter.load_state_dict(state, len(self.store))
            self.store.env_steps_total = self.limiter.env_steps
            self.restored_episodes, self.restore_skipped = len(self.store), restored.skipped
            self.snapshot_taken = restored.taken
            self.snapshot_stats["snapshot_bytes"] = self.snapshotter.total_bytes
            self.snapshot_stats["snapshot_episodes"] = len(restored.episodes)
        return source
