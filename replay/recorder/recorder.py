"""The flight recorder: every message of a run, as sent, into one MCAP file.

It subscribes to ``<namespace>/<run>/**``. Zenoh calls back on its own threads; the
callback only copies the payload, stamps the reception time and offers it to a
bounded hand-off, so the recorder never slows a publisher: what does not fit is
dropped and counted (per key, in the recorder's Stats and in the file's
``d3rqn.recorder`` metadata; the per-key sequence numbers show the gaps). A
writer thread does everything else: time stamps, weights sampling, views,
compression, and a flush every ``recorder.flush_period_s`` that closes the open
chunk, so a recorder killed with SIGKILL leaves a file readable up to that flush
(``d3rqn-log recover``). A full disk pauses the recording: the file is cut back to its last flush, and once
space returns the recording goes on in the next numbered file.

Weights (48 MB each) are kept sparsely: the first, one per
``recorder.weights_every_versions`` versions, and the newest one when recording stops.
Queries (trace batches, latest weights) are not publications and are not recorded.

With a TensorBoard folder, the writer thread also turns what it writes into the run's
curves (``tensorboard_events.py``), flushed with the log; if that writer fails, it is
logged and dropped and the recording goes on.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, deque
from pathlib import Path
from typing import Callable

import zenoh

from common.config import Config, RecorderConfig
from common.disk_space import free_bytes, is_disk_full, size_text
from common.run_dir import RunDir, next_free_path
from common.shell import Shell
from common.transport import Declared, publisher
from common.logs import ThrottledLog
from common.wire.messages import Stats, Weights
from replay.recorder.arrival import Arrival, Peek, peek
from replay.recorder.tensorboard_events import EventsWriter
from replay.recorder.views import ViewMaker
from replay.recorder.writer import MEGABYTE, LogWriter

log = logging.getLogger("recorder")

PAUSE_POLL_S = 1.0  # how often a recording paused for a full disk looks for space
# the free space a paused recording waits for: a few chunks, so that it does not pause again at once
RESUME_CHUNKS, RESUME_MIN_BYTES = 4, 32 * MEGABYTE


class HandOff:
    """A FIFO bounded in items and bytes; offering never waits, taking waits up to a timeout."""

    def __init__(self, max_items: int, max_bytes: int) -> None:
        self.max_items = max_items
        self.max_bytes = max_bytes
        self._items: deque[tuple[object, int]] = deque()
        self._bytes = 0
        self._closed = False
        self._ready = threading.Condition()

    def offer(self, item: object, size: int) -> bool:
        """Queues the item unless it does not fit (or the hand-off is closed); returns whether it was queued."""
        with self._ready:
            if self._closed or len(self._items) >= self.max_items or self._bytes + size > self.max_bytes:
                return False
            self._items.append((item, size))
            self._bytes += size
            self._ready.notify()
            return True

    def take(self, timeout_s: float) -> object | None:
        """The oldest item, or None if none came within the timeout (or the hand-off is closed and empty)."""
        with self._ready:
            if not self._items and not self._closed:
                self._ready.wait(timeout_s)
            if not self._items:
                return None
            item, size = self._items.popleft()
            self._bytes -= size
            return item

    def close(self) -> None:
        """Refuses new items; take() still returns those queued."""
        with self._ready:
            self._closed = True
            self._ready.notify_all()

    @property
    def drained(self) -> bool:
        with self._ready:
            return self._closed and not self._items

    def depth(self) -> tuple[int, int]:
        with self._ready:
            return len(self._items), self._bytes


class WeightsSampler:
    """Keeps the first Weights, then one per `every` versions; holds the newest skipped one for the end."""

    def __init__(self, every: int) -> None:
        self.every = every
        self.last_kept: int | None = None
        self.held: tuple[Arrival, Peek] | None = None
        self.kept = 0
        self.skipped = 0

    def keep(self, arrival: Arrival, seen: Peek) -> bool:
        version = seen.version
        if version is None:
            self.kept += 1
            return True  # a Weights message without a readable version is kept as evidence
        if self.last_kept is None or version >= self.last_kept + self.every:
            self.last_kept = version
            self.kept += 1
            return True
        if version > self.last_kept:
            self.held = (arrival, seen)
        self.skipped += 1
        return False

    def take_held(self) -> tuple[Arrival, Peek] | None:
        """The newest skipped Weights if it is newer than the last kept one: the run's final weights."""
        held, self.held = self.held, None
        if held is None or held[1].version <= self.last_kept:
            return None
        self.last_kept = held[1].version
        self.kept += 1
        self.skipped -= 1
        return held


class Recorder:
    """Samples in through `offer`, file out through a writer thread.

    Given `reopen` (a new LogWriter for the next file), a full disk pauses the recording instead of ending it:
    the file is cut back to its last flush (readable so far), what arrives meanwhile is dropped and counted,
    and once `free_space()` is at least resume_bytes again the recording goes on in the file reopen gives."""

    def __init__(self, writer: LogWriter, config: RecorderConfig, board: EventsWriter | None = None,
                 reopen: Callable[[], LogWriter] | None = None,
                 free_space: Callable[[], int | None] | None = None) -> None:
        self.writer: LogWriter | None = writer  # None once it was abandoned and no other opened before the end
        self.path = writer.path  # of the latest file
        self._reopen = reopen
        self._free_space = free_space or (lambda: free_bytes(writer.path.parent))
        self.resume_bytes = max(RESUME_CHUNKS * int(config.chunk_mb * MEGABYTE), RESUME_MIN_BYTES)
        self.pauses = 0
        self._earlier = (0, 0)  # wire and view messages of the files written before this one
        self.board = board
        self.flush_period_s = config.flush_period_s
        self.handoff = HandOff(config.queue_messages, int(config.queue_mb * MEGABYTE))
        self.sampler = WeightsSampler(config.weights_every_versions)
        self._lock = threading.Lock()
        self._sequences: dict[str, int] = {}
        self.received = 0
        self.dropped: Counter[str] = Counter()
        self.error: BaseException | None = None
        self._warn = ThrottledLog(logger=log)
        self._thread = threading.Thread(target=self._write_all, name="mcap-writer", daemon=True)

    # --- Zenoh's side: copy, stamp, hand off ---------------------------------------------------

    def on_sample(self, sample: zenoh.Sample) -> None:
        received_ns = time.time_ns()
        if sample.kind != zenoh.SampleKind.PUT:
            return
        stamp = sample.timestamp
        zenoh_ns = None if stamp is None else stamp.get_time_as_ntp64().as_nanos()
        self.offer(str(sample.key_expr), sample.payload.to_bytes(), received_ns, zenoh_ns)

    def offer(self, key: str, data: bytes, received_ns: int, zenoh_ns: int | None = None) -> bool:
        with self._lock:
            sequence = self._sequences[key] = self._sequences.get(key, 0) + 1
            self.received += 1
        if self.handoff.offer(Arrival(key, data, received_ns, zenoh_ns, sequence), len(data)):
            return True
        with self._lock:
            self.dropped[key] += 1
        self._warn.warning("recorder queue full: dropped a %d-byte message on %s", len(data), key)
        return False

    # --- the writer thread -----------------------------------------------------------------------

    def start(self) -> None:
        self._thread.start()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def stop(self) -> None:
        """Writes what is queued and the newest weights, then closes the file."""
        self.handoff.close()
        self._thread.join()
        if self.error is None and self.writer is not None:
            self._finish(self.writer)
        self._to_board(lambda board: board.close())

    def _finish(self, writer: LogWriter) -> None:
        try:
            held = self.sampler.take_held()
            if held is not None:
                writer.write(*held)
            writer.close({key: str(value) for key, value in self.snapshot().items()})
        except OSError as error:
            if not is_disk_full(error):
                raise
            writer.abandon()
            log.error("the disk is full: %s ends without its summary; it reads up to its last flush", writer.path)

    def _write_all(self) -> None:
        try:
            while True:
                try:
                    return self._write_until_drained()
                except Exception as error:
                    if self._reopen is None or not is_disk_full(error):
                        raise
                    if not self._pause(error):
                        return
        except Exception as error:  # a closed file, a bug...: stop writing; the file stays recoverable
            self.error = error
            log.exception("the writer failed; recording stops")

    def _write_until_drained(self) -> None:
        next_flush = time.monotonic() + self.flush_period_s
        while not self.handoff.drained:
            arrival = self.handoff.take(max(0.0, next_flush - time.monotonic()))
            if arrival is not None:
                self._write(arrival)
            if time.monotonic() >= next_flush:
                self.writer.flush()
                self._to_board(lambda board: board.flush())
                next_flush = time.monotonic() + self.flush_period_s

    def _pause(self, error: BaseException) -> bool:
        """Abandons the file the disk refused, drops what arrives until space returns, then goes on in a new
        file: True; False where recording stopped meanwhile."""
        writer, self.writer = self.writer, None
        writer.abandon()
        self.pauses += 1
        self._earlier = (self._earlier[0] + writer.messages, self._earlier[1] + writer.view_messages)
        log.error("the disk is full (%s, %s free): recording pauses and drops what arrives; %s reads up to its "
                  "last flush (%s); it goes on in a new file once %s are free", error,
                  size_text(self._free_space()), writer.path, size_text(writer.flushed_bytes),
                  size_text(self.resume_bytes))
        while not self.handoff.drained:
            free = self._free_space()
            if free is None or free >= self.resume_bytes:
                try:
                    self.writer = self._reopen()
                except OSError as again:
                    if not is_disk_full(again):
                        raise
                else:
                    self.path = self.writer.path
                    log.info("space is back (%s free): recording goes on in %s", size_text(free), self.path)
                    return True
            self._drop_for(PAUSE_POLL_S)
        return False

    def _drop_for(self, seconds: float) -> None:
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0 and not self.handoff.drained:
            arrival = self.handoff.take(left)
            if arrival is not None:
                with self._lock:
                    self.dropped[arrival.key] += 1

    def _write(self, arrival: Arrival) -> None:
        seen = peek(arrival.data)
        if seen.message_type == Weights.__name__ and not self.sampler.keep(arrival, seen):
            return
        self.writer.write(arrival, seen)
        self._to_board(lambda board: board.add_wire(arrival.key, arrival.data, arrival.received_ns,
                                                    seen.message_type))

    def _to_board(self, action) -> None:
        """action(the TensorBoard writer), if there is one; one that fails is dropped, the log goes on."""
        if self.board is None:
            return
        try:
            action(self.board)
        except Exception:  # disk full, a folder removed...: the curves are a copy, the log is what counts
            log.exception("the TensorBoard writer failed; recording goes on without it")
            self.board = None

    def snapshot(self) -> dict[str, int | float]:
        depth, queued_bytes = self.handoff.depth()
        with self._lock:
            dropped = dict(self.dropped)
            received = self.received
        writer, (written, views) = self.writer, self._earlier
        if writer is not None:
            written, views = written + writer.messages, views + writer.view_messages
        values: dict[str, int | float] = {
            "received": received, "written": written, "views_written": views, "pauses": self.pauses,
            "paused": int(writer is None), "dropped": sum(dropped.values()),
            "queue_messages": depth, "queue_mb": queued_bytes / MEGABYTE,
            "weights_kept": self.sampler.kept, "weights_skipped": self.sampler.skipped,
        }
        values.update({f"dropped:{key}": count for key, count in dropped.items()})
        return values


def default_log_path(config: Config) -> Path:
    """The run's wire log; a recorder never overwrites one (next_free_path numbers the next)."""
    return RunDir.of(config).wire_log


def run_recorder(config: Config, output: Path | None = None, tensorboard: Path | None = None) -> int:
    """Records until SIGINT/SIGTERM, with TensorBoard event files in `tensorboard` if given; returns the
    exit code (1 if the writer failed)."""
    shell = Shell("recorder", config, sole=False)  # several may record a run
    keys = shell.keys
    path = next_free_path(output or default_log_path(config))
    path.parent.mkdir(parents=True, exist_ok=True)
    views = None
    if config.recorder.views:
        views = ViewMaker(keys.root, 1.0 / config.env.policy_frequency, config.recorder.images,
                          config.recorder.image_format)
    board = None if tensorboard is None else EventsWriter(tensorboard, keys.root)
    with shell.session() as session:
        recorder = Recorder(LogWriter.open(path, config, views), config.recorder, board,
                            reopen=lambda: LogWriter.open(next_free_path(path), config, views))
        recorder.start()
        shell.on_close(recorder.stop)  # once nothing more arrives: after the subscription's undeclare
        subscription = Declared(keys.all).attach(session.declare_subscriber(keys.all, recorder.on_sample))
        stats_out = publisher(session, keys.metrics_source("recorder", "0"), reliable=False)
        shell.on_close(subscription.undeclare)
        shell.on_close(stats_out.undeclare)
        log.info("recording %s into %s%s", keys.all, path, "" if board is None else f", curves into {tensorboard}")
        while recorder.alive and not shell.stop.wait(config.recorder.stats_period_s):
            values = recorder.snapshot()
            stats_out.put(Stats(source="recorder", time=time.time(), values=values))
            log.info("received %(received)d, written %(written)d, dropped %(dropped)d, "
                     "queue %(queue_messages)d (%(queue_mb).1f MB)", values)
    log.info("stopped; %s: %s", recorder.path, recorder.snapshot())
    return 1 if recorder.error is not None else 0
