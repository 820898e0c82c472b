"""TensorBoard event files of a run's curves: written live by the recorder (``d3rqn-log record
--tensorboard DIR``, ``deploy/launcher/stack.py --tensorboard``) and from a log by ``d3rqn-log export
--tensorboard DIR``, the same series (``scalars.py``) either way.

Every point is one scalar event with step = its env steps and wall time = its log time, so
TensorBoard's STEP axis is the run's env steps and RELATIVE and WALL are the run's clock.
The writer is tensorboard's own event-file writer, the one torch's SummaryWriter is built on:
it needs neither torch nor TensorFlow, so the recorder stays a small process.
"""

from __future__ import annotations

from pathlib import Path

from tensorboard.compat.proto.event_pb2 import Event
from tensorboard.compat.proto.summary_pb2 import Summary
from tensorboard.summary.writer.event_file_writer import EventFileWriter

from common.wire.codecs import Message
from common.wire.envelope import decode
from common.wire.errors import WireError
from replay.recorder.reader import LogFile
from replay.recorder.scalars import CURVE_TYPE_NAMES, CURVE_TYPES, Curves, Point

EVENT_FILE_PATTERN = "events.out.tfevents.*"
QUEUE_EVENTS = 1000  # events handed to the file writer's thread before a write waits


class EventsWriter:
    """One new event file in `directory` (TensorBoard shows all the files of a folder as one run)."""

    def __init__(self, directory: Path, run_root: str) -> None:
        self._file = EventFileWriter(str(directory), max_queue_size=QUEUE_EVENTS)
        self.curves = Curves(run_root)
        self.points = 0

    def add(self, key: str, message: Message, log_ns: int) -> None:
        self._write(self.curves.add(key, message, log_ns))

    def add_wire(self, key: str, data: bytes, log_ns: int, message_type: str | None) -> None:
        """A recorded wire message: only those of a type with curves are decoded; malformed ones are skipped."""
        if message_type not in CURVE_TYPE_NAMES:
            return
        try:
            message = decode(data)
        except WireError:
            return
        self.add(key, message, log_ns)

    def flush(self) -> None:
        self._file.flush()

    def close(self) -> None:
        """Writes the points still waiting for the run's env-step count, then closes the file."""
        self._write(self.curves.finish())
        self._file.close()

    def _write(self, points: list[tuple[str, Point]]) -> None:
        for tag, point in points:
            summary = Summary(value=[Summary.Value(tag=tag, simple_value=point.value)])
            self._file.add_event(Event(wall_time=point.wall_s, step=point.env_steps, summary=summary))
        self.points += len(points)


def export_tensorboard(log: LogFile, directory: Path) -> int:
    """Writes the log's curves into a folder without event files; returns the number of points."""
    if directory.is_dir() and any(directory.glob(EVENT_FILE_PATTERN)):
        raise FileExistsError(f"{directory}: already holds TensorBoard event files, which TensorBoard would show "
                              f"mixed with these; choose an empty or new folder")
    writer = EventsWriter(directory, log.keys().root)
    try:
        for record, message in log.messages(*CURVE_TYPES):
            writer.add(record.topic, message, record.log_ns)
    finally:
        writer.close()
    return writer.points
