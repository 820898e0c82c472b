"""Keeps trace-batch requests in flight so an update never waits on the network."""

from __future__ import annotations

import itertools
import logging
import queue
import threading
import time
from typing import Callable

from common.wire.messages import TraceBatch, TraceBatchRequest

log = logging.getLogger("learner.prefetch")

RETRY_PAUSE_S = 0.1  # after no reply: the replay drops a request it held too long


class Prefetcher:
    """`depth` worker threads, each asking for the next batch as soon as its last one is queued.

    `fetch(request)` is the transport call (a Zenoh get in production, a function
    in tests); it returns a TraceBatch or None (no reply, timeout, empty replay). The
    replay holds a reply back while its rate limiter says the learner is ahead, so a
    worker's wait for its batch is the learner's pacing.

    `prepare(batch)`, if given, runs in the worker too, and next() returns what it
    returns: the place to decode frames and stage them on the learner's device
    (learner.trace_batch.BatchStager) while the previous update runs. An exception it
    raises is raised by the next() that would have returned its result.
    """

    def __init__(self, fetch: Callable[[TraceBatchRequest], TraceBatch | None],
                 batch_size: int, trace_length: int, depth: int,
                 prepare: Callable[[TraceBatch], object] | None = None) -> None:
        self._fetch = fetch
        self._prepare = prepare
        self._batch_size = batch_size
        self._trace_length = trace_length
        self._ready: queue.Queue[TraceBatch] = queue.Queue(maxsize=depth)
        self._ids = itertools.count()
        self._ids_lock = threading.Lock()
        self._stop = threading.Event()
        self.wait_s = 0.0  # time the consumer spent waiting for a batch
        self._threads = [threading.Thread(target=self._work, daemon=True, name=f"prefetch-{n}")
                         for n in range(depth)]
        for thread in self._threads:
            thread.start()

    def next(self, stop: threading.Event, timeout_s: float | None = None) -> TraceBatch | None:
        """The next batch, or None once `stop` is set or after timeout_s seconds without one."""
        started = time.monotonic()
        try:
            while not stop.is_set():
                if timeout_s is not None and time.monotonic() - started >= timeout_s:
                    return None
                try:
                    item = self._ready.get(timeout=0.1)
                except queue.Empty:
                    continue
                if isinstance(item, _Failed):
                    raise item.error
                return item
            return None
        finally:
            self.wait_s += time.monotonic() - started

    def close(self, timeout_s: float = 1.0) -> None:
        """Stops the workers; one still waiting on a held request is left to end with the process
        (daemon threads), so stopping never waits for the replay."""
        self._stop.set()
        deadline = time.monotonic() + timeout_s
        for thread in self._threads:
            thread.join(timeout=max(0.0, deadline - time.monotonic()))

    def _work(self) -> None:
        while not self._stop.is_set():
            with self._ids_lock:
                request_id = next(self._ids)
            batch = self._fetch(TraceBatchRequest(request_id=request_id, batch_size=self._batch_size,
                                                  trace_length=self._trace_length))
            if batch is None:
                self._stop.wait(RETRY_PAUSE_S)
                continue
            if self._prepare is not None:
                try:
                    batch = self._prepare(batch)
                except Exception as error:  # handed to the consumer, which would have met it in the update
                    batch = _Failed(error)
            while not self._stop.is_set():
                try:
                    self._ready.put(batch, timeout=0.1)
                    break
                except queue.Full:
                    continue


class _Failed:
    def __init__(self, error: Exception) -> None:
        self.error = error
