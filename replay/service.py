"""The replay service: episodes in over Zenoh, trace batches out on a queryable, stats out.

It owns the system's one rate limiter (replay/rate_limiter.py): it counts every
env step received and every trace batch served, holds a batch request back while
the learner is ahead, and publishes on ``replay/rate`` whether the actors must
hold their next episode (the learner is behind, or the run's budget is spent).

Zenoh delivers on its own threads, which only park what arrives: every touch of
the store and the limiter holds one lock, and held requests are answered by the
service's reply threads. A malformed or oversized message is logged, counted and
dropped; nothing stored is lost because of it.
"""

from __future__ import annotations

import json
import logging
import math
import os
import signal
import threading
import time
from collections import deque
from pathlib import Path

from common.config import Config
from common.logs import Every, setup_logging
from common.transport import (
    Keys, PendingQuery, RateLimitedLog, declare_liveliness, open_session, publisher, serve_deferred, subscribe,
)
from common.wire import Episode, ExplorationState, Stats, TraceBatchRequest
from replay.rate_limiter import RateLimiter, rate_limit_from_config
from replay.store import EpisodeStore, full_episodes_fit

log = logging.getLogger("replay")

MEGABYTE = 1 << 20
KILOBYTE = 1 << 10
HOLD_MAX_S = 10.0  # a held request is dropped after this (the learner asks again); below its 30 s timeout
REPLY_THREADS = 2
WAKE_S = 0.1  # reply threads look at expiries and the rate message at least this often
MEASURE_AFTER_FRAMES = 1_000  # the budget check is repeated once with the measured frame size
COUNTERS_FILE = "rate_limiter.json"
RATE_SOURCE = "rate_limiter"  # the Stats source of replay/rate messages (replay/stats: "replay")


def counters_path(config: Config) -> Path:
    """Where the replay keeps its rate limiter's counters: <runs_dir>/<run>/replay/rate_limiter.json."""
    return Path(config.run.runs_dir) / config.run.name / "replay" / COUNTERS_FILE


class ReplayService:
    """The store and the rate limiter behind one lock, the held requests, and the counters the stats report."""

    def __init__(self, config: Config) -> None:
        self.config = config
        self.store = EpisodeStore(
            capacity=config.replay.capacity,
            budget_bytes=int(config.replay.memory_budget_mb * MEGABYTE),
            trace_length=config.learner.trace_length,
            seed=config.replay.seed,
        )
        self.limiter = RateLimiter(rate_limit_from_config(config))
        self.max_trace_batch = config.replay.max_batch_size
        self._lock = threading.Lock()
        self._changed = threading.Condition(self._lock)
        self._pending: deque[PendingQuery] = deque()
        self.traces_served = 0
        self.rejected_requests = 0
        self.expired_requests = 0
        self.learner_strategy: str | None = None
        self._measured = False
        self._warn_budget = RateLimitedLog(60.0)
        self._announced: tuple[str, int] | None = None  # the hold reason and env steps last published on replay/rate

    # --- inputs from Zenoh callbacks (never wait) ----------------------------------------

    def on_episode(self, episode: Episode, key: str = "") -> None:
        if not isinstance(episode, Episode):
            return
        with self._lock:
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
        if not isinstance(request, TraceBatchRequest) or request.trace_length != self.store.trace_length \
                or not 0 < request.batch_size <= self.max_trace_batch:
            with self._lock:
                self.rejected_requests += 1
            shown = (f"{request.batch_size} traces of {request.trace_length} steps"
                     if isinstance(request, TraceBatchRequest) else repr(request))
            log.warning("rejected a request for %s (serving up to %d traces of %d steps)",
                        shown, self.max_trace_batch, self.store.trace_length)
            pending.drop()
            return
        with self._lock:
            self._pending.append(pending)
            self._changed.notify_all()

    def on_exploration(self, state: ExplorationState, key: str = "") -> None:
        """The learner's strategy decides the start rule (decreasing epsilon starts by steps)."""
        if not isinstance(state, ExplorationState):
            return
        with self._lock:
            if state.strategy == self.learner_strategy:
                return
            self.learner_strategy = state.strategy
            by_steps = state.strategy == "decreasing"
            changed = by_steps != self.limiter.limit.start_by_steps
            accepted = self.limiter.set_start_by_steps(by_steps)
        if changed and accepted:
            log.info("the learner's strategy is %s: updates start at %s", state.strategy,
                     f"{self.config.learner.start_steps} env steps" if by_steps
                     else f"{self.config.learner.start_episodes} episodes")
        elif not accepted:
            log.warning("the learner's strategy is %s, but updates already started by the other rule "
                        "(this replay was configured for %s)", state.strategy, self.config.exploration.strategy)

    # --- the reply threads ---------------------------------------------------------------

    def serve_pending(self, stop: threading.Event, announce=None) -> None:
        """Answers held requests while the limiter allows; calls announce(values) when the actors'
        hold changes and at least every stats period. Runs until stop is set; an error is logged
        and the thread goes on."""
        every = Every(self.config.replay.stats_period_s)
        warn = RateLimitedLog()
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
                # a change of the hold; past the budget every new step too (the learner pays the last ones)
                reason = self.limiter.hold_reason()
                now = (reason, self.limiter.env_steps if reason == "budget" else 0)
                announce_now = now != self._announced or every.due()
                if announce_now:
                    self._announced = now
                    values = self.limiter.values()
            if served is None and not announce_now and not expired:
                self._changed.wait(WAKE_S)
        for pending in expired:
            pending.drop()
        if announce_now:  # first: the actors' release is what the learner waits for next
            announce(values)
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
        except Exception as error:
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
        replay, max_steps = self.config.replay, self.config.env.max_steps
        fits = full_episodes_fit(self.store.budget_bytes, max_steps, frame_bytes)
        needed_mb = math.ceil(replay.capacity * ((max_steps + 1) * frame_bytes + max_steps * 20) / MEGABYTE)
        if fits >= replay.capacity:
            log.info("memory budget %.0f MB holds %d episodes of env.max_steps = %d steps at %.2f KB per frame "
                     "(%s): replay.capacity %d fits", replay.memory_budget_mb, fits, max_steps,
                     frame_bytes / KILOBYTE, source, replay.capacity)
            return True
        log.warning("REPLAY.CAPACITY DOES NOT FIT: replay.memory_budget_mb %.0f holds only %d of %d episodes of "
                    "env.max_steps = %d steps at %.2f KB per frame (%s); once episodes grow long the budget "
                    "evicts early. Set --replay.memory_budget_mb %d (or more) to hold the configured buffer",
                    replay.memory_budget_mb, fits, replay.capacity, max_steps, frame_bytes / KILOBYTE, source,
                    needed_mb)
        return False

    def _check_measured_budget(self) -> None:
        if not self._measured and self.store.frames >= MEASURE_AFTER_FRAMES:
            self._measured = True
            self.budget_report(self.store.frame_bytes_mean, f"measured over {self.store.frames} frames")

    # --- counters ------------------------------------------------------------------------

    def snapshot(self) -> dict[str, int | float | str]:
        with self._lock:
            store = self.store
            values: dict[str, int | float | str] = {
                "episodes": len(store), "frames": store.frames, "bytes": store.bytes,
                "inserted": store.inserted, "evicted": store.evicted,
                "evicted_for_budget": store.evicted_for_budget, "short_dropped": store.short_dropped,
                "env_steps_total": store.env_steps_total, "traces_served": self.traces_served,
                "rejected_requests": self.rejected_requests, "expired_requests": self.expired_requests,
                "pending_requests": len(self._pending),
            }
            if store.frames:
                values["frame_bytes_mean"] = store.frame_bytes_mean
            values.update({f"rate_{name}": value for name, value in self.limiter.values().items()})
            return values

    def limiter_state(self) -> dict:
        with self._lock:
            return self.limiter.state_dict()

    def load_limiter_state(self, state: dict) -> None:
        """Counters of this run's earlier replay; the store restarts empty."""
        with self._lock:
            self.limiter.load_state_dict(state)
            self.store.env_steps_total = self.limiter.env_steps


def save_counters(path: Path, state: dict) -> None:
    """Atomic: a temporary file renamed over the old one."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    temporary.write_text(json.dumps(state))
    os.replace(temporary, path)


class RateMeter:
    """Per-second rates of growing counters between two snapshots."""

    def __init__(self, clock=time.monotonic) -> None:
        self._clock = clock
        self._last_time = clock()
        self._last: dict[str, float] = {}

    def rates(self, counters: dict[str, float], names: tuple[str, ...]) -> dict[str, float]:
        now = self._clock()
        elapsed = max(now - self._last_time, 1e-9)
        rates = {f"{name}_per_s": (counters[name] - self._last.get(name, 0)) / elapsed for name in names}
        self._last_time, self._last = now, dict(counters)
        return rates


def physical_memory_bytes() -> int | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def run_replay(config: Config, resume: bool = False) -> None:
    """Serves until SIGINT/SIGTERM; with resume, continues the counters of the run's earlier replay."""
    setup_logging("replay")
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    service = ReplayService(config)
    path = counters_path(config)
    if resume:
        _resume_counters(service, path)
    _check_budget_at_start(service, config)
    keys = Keys(config.transport.namespace, config.run.name)
    max_bytes = int(config.replay.max_message_mb * MEGABYTE)
    session = open_session(config.transport)
    threads: list[threading.Thread] = []
    try:
        liveliness = declare_liveliness(session, keys.liveliness("replay", "0"))
        episodes = subscribe(session, keys.episodes, service.on_episode, max_bytes=max_bytes)
        exploration = subscribe(session, keys.exploration, service.on_exploration, expected=ExplorationState)
        queryable = serve_deferred(session, keys.replay_sample, service.on_sample_request, expected=TraceBatchRequest)
        stats_out = publisher(session, keys.replay_stats)
        rate_out = publisher(session, keys.replay_rate)

        def announce(values: dict) -> None:
            rate_out.put(Stats(source=RATE_SOURCE, time=time.time(), values=values))

        threads = [threading.Thread(target=service.serve_pending, args=(stop, announce if n == 0 else None),
                                    name=f"reply-{n}", daemon=True) for n in range(REPLY_THREADS)]
        for thread in threads:
            thread.start()
        log.info("serving run %r: capacity %d episodes, budget %.0f MB, traces of %d steps, "
                 "1 update per %g env steps within %g updates", config.run.name, config.replay.capacity,
                 config.replay.memory_budget_mb, config.learner.trace_length, config.learner.env_steps_per_update,
                 config.replay.error_buffer_updates)
        _report_until(stop, service, episodes, stats_out, config, path)
        for thread in threads:
            thread.join(timeout=5.0)
        service.drop_pending()
        for declared in (queryable, exploration, episodes, liveliness):
            declared.undeclare()
    finally:
        stop.set()
        session.close()
    try:
        save_counters(path, service.limiter_state())
    except OSError as error:
        log.warning("cannot save the rate limiter's counters to %s: %s", path, error)
    log.info("stopped; %s", service.snapshot())


def _resume_counters(service: ReplayService, path: Path) -> None:
    try:
        service.load_limiter_state(json.loads(path.read_text()))
    except FileNotFoundError:
        log.warning("--resume: no counters at %s; counting this run's env steps and batches from zero", path)
        return
    except (OSError, ValueError) as error:
        log.warning("--resume: cannot use the counters in %s (%s); counting from zero", path, error)
        return
    limiter = service.limiter
    log.info("resumed the rate limiter from %s: %d env steps, %d batches served, start mark %s%s", path,
             limiter.env_steps, limiter.served, "none" if limiter.start_mark is None else f"{limiter.start_mark:.0f}",
             f"; the store is empty: batches wait until it holds {limiter.limit.start_episodes} episodes again "
             "(the refill's steps are not owed)" if limiter.refilling else "")


def _check_budget_at_start(service: ReplayService, config: Config) -> None:
    service.budget_report(config.replay.frame_kb_estimate * KILOBYTE, "replay.frame_kb_estimate")
    memory = physical_memory_bytes()
    if memory is not None and config.replay.memory_budget_mb * MEGABYTE > memory:
        log.warning("replay.memory_budget_mb %.0f exceeds this machine's %.0f MB of memory: a full buffer "
                    "would not fit", config.replay.memory_budget_mb, memory / MEGABYTE)


def _report_until(stop: threading.Event, service: ReplayService, episodes, stats_out, config: Config,
                  path: Path) -> None:
    meter = RateMeter()
    log_every = Every(config.replay.log_period_s)
    warn = RateLimitedLog()
    while not stop.wait(config.replay.stats_period_s):
        values = service.snapshot()
        values["rejected_messages"] = episodes.rejected
        values.update(meter.rates(values, ("inserted", "traces_served", "env_steps_total")))
        stats_out.put(Stats(source="replay", time=time.time(), values=values))
        try:
            save_counters(path, service.limiter_state())
        except OSError as error:
            warn.warning("cannot save the rate limiter's counters to %s: %s", path, error)
        if log_every.due():
            log.info("episodes %(episodes)d (%(bytes)d B), env steps %(env_steps_total)d, "
                     "inserted %(inserted)d, traces served %(traces_served)d, short %(short_dropped)d, "
                     "rejected %(rejected_messages)d; updates due %(rate_updates_due).1f, batches served "
                     "%(rate_batches_served)d, actors hold: %(rate_hold_reason)s",
                     {**values, "rate_hold_reason": values["rate_hold_reason"] or "no"})
