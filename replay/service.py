"""The replay service: episodes in over Zenoh, trace batches out on a queryable, stats out.

Zenoh delivers on its own threads, so every touch of the store holds one lock.
A malformed or oversized message is logged, counted and dropped; nothing stored
is lost because of it.
"""

from __future__ import annotations

import logging
import signal
import threading
import time

from common.config import Config
from common.logs import Every, setup_logging
from common.transport import Keys, declare_liveliness, open_session, publisher, serve, subscribe
from common.wire import Episode, Stats, TraceBatch, TraceBatchRequest
from replay.store import EpisodeStore

log = logging.getLogger("replay")

MEGABYTE = 1 << 20


class ReplayService:
    """The store behind a lock, plus the counters the stats report."""

    def __init__(self, config: Config) -> None:
        self.config = config
        self.store = EpisodeStore(
            capacity=config.replay.capacity,
            budget_bytes=int(config.replay.memory_budget_mb * MEGABYTE),
            trace_length=config.learner.trace_length,
            seed=config.replay.seed,
        )
        self.max_trace_batch = config.replay.max_batch_size
        self._lock = threading.Lock()
        self.traces_served = 0
        self.rejected_requests = 0

    def on_episode(self, episode: Episode, key: str = "") -> None:
        if not isinstance(episode, Episode):
            return
        with self._lock:
            self.store.add(episode)

    def on_sample(self, request: TraceBatchRequest) -> TraceBatch | None:
        """Answers a trace-batch request, or None while no episode can be sampled."""
        if not isinstance(request, TraceBatchRequest):
            return None
        if request.trace_length != self.store.trace_length or not 0 < request.batch_size <= self.max_trace_batch:
            with self._lock:
                self.rejected_requests += 1
            log.warning("rejected a request for %d traces of %d steps (serving up to %d traces of %d steps)",
                        request.batch_size, request.trace_length, self.max_trace_batch, self.store.trace_length)
            return None
        with self._lock:
            if len(self.store) == 0:
                return None
            batch = self.store.sample(request.batch_size, request.request_id)
            self.traces_served += request.batch_size
        return batch

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            store = self.store
            return {
                "episodes": len(store), "frames": store.frames, "bytes": store.bytes,
                "inserted": store.inserted, "evicted": store.evicted, "short_dropped": store.short_dropped,
                "env_steps_total": store.env_steps_total, "traces_served": self.traces_served,
                "rejected_requests": self.rejected_requests,
            }


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


def run_replay(config: Config) -> None:
    """Serves until SIGINT/SIGTERM."""
    setup_logging("replay")
    stop = threading.Event()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda *_: stop.set())
    service = ReplayService(config)
    keys = Keys(config.transport.namespace, config.run.name)
    max_bytes = int(config.replay.max_message_mb * MEGABYTE)
    session = open_session(config.transport)
    try:
        liveliness = declare_liveliness(session, keys.liveliness("replay", "0"))
        episodes = subscribe(session, keys.episodes, service.on_episode, max_bytes=max_bytes)
        queryable = serve(session, keys.replay_sample, service.on_sample)
        stats_out = publisher(session, keys.replay_stats)
        log.info("serving run %r: capacity %d episodes, budget %.0f MB, traces of %d steps",
                 config.run.name, config.replay.capacity, config.replay.memory_budget_mb,
                 config.learner.trace_length)
        _report_until(stop, service, episodes, stats_out, config)
        for declared in (queryable, episodes, liveliness):
            declared.undeclare()
    finally:
        session.close()
    log.info("stopped; %s", service.snapshot())


def _report_until(stop: threading.Event, service: ReplayService, episodes, stats_out, config: Config) -> None:
    meter = RateMeter()
    log_every = Every(config.replay.log_period_s)
    while not stop.wait(config.replay.stats_period_s):
        values = service.snapshot()
        values["rejected_messages"] = episodes.rejected
        values.update(meter.rates(values, ("inserted", "traces_served", "env_steps_total")))
        stats_out.put(Stats(source="replay", time=time.time(), values=values))
        if log_every.due():
            log.info("episodes %(episodes)d (%(bytes)d B), env steps %(env_steps_total)d, "
                     "inserted %(inserted)d, traces served %(traces_served)d, short %(short_dropped)d, "
                     "rejected %(rejected_messages)d", values)
