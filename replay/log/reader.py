"""Reading a log back: a whole, sound MCAP file, or one clear LogError.

A file whose end is missing (a recorder killed before it finished) is refused with
a pointer to ``d3rqn-log recover``; damaged data raises LogError when it is read
(chunk CRCs are checked), never a library exception.
"""

from __future__ import annotations

import struct
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import zstandard
from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel
from mcap.stream_reader import MAGIC_SIZE

from common.config import Config, ConfigError, from_dict
from common.transport import Keys
from common.wire import Message, WireError, decode
from replay.log.traffic import CONFIG_METADATA, RECORDER_METADATA, WIRE_ENCODING

MCAP_MAGIC = b"\x89MCAP0\r\n"
# What the mcap library raises on damaged input: its own errors and those of struct, zstd and plain Python.
DAMAGED = (McapError, struct.error, ValueError, KeyError, IndexError, EOFError, OverflowError, zstandard.ZstdError)


class LogError(Exception):
    """A log cannot be read; the message is one line naming the file and the fault."""


@dataclass(frozen=True)
class Record:
    topic: str
    encoding: str  # "msgpack" for wire traffic, "json" for views
    message_type: str  # the wire type from the channel metadata, or the view's schema name
    data: bytes
    log_ns: int
    publish_ns: int
    sequence: int


def check_ends(path: Path, head: bytes, tail: bytes) -> None:
    """The MCAP magic must open and close the file; a missing end means an unfinished recording."""
    if head != MCAP_MAGIC:
        raise LogError(f"{path}: not an MCAP file (it does not start with the MCAP magic)")
    if tail != MCAP_MAGIC:
        raise LogError(f"{path}: unfinished or truncated MCAP file (no footer at its end; was the recorder "
                       f"killed?); `d3rqn-log recover {path} FIXED.mcap` rewrites what it holds")


class LogFile:
    """An open log; use as a context manager."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self._handle = open(self.path, "rb")
        except OSError as error:
            raise LogError(f"{self.path}: cannot open ({error.strerror})") from None
        try:
            self.size_bytes = self._handle.seek(0, 2)
            if self.size_bytes < 2 * MAGIC_SIZE:
                raise LogError(f"{self.path}: not an MCAP file ({self.size_bytes} bytes)")
            self._handle.seek(0)
            head = self._handle.read(MAGIC_SIZE)
            self._handle.seek(-MAGIC_SIZE, 2)
            check_ends(self.path, head, self._handle.read(MAGIC_SIZE))
            self._handle.seek(0)
            self._reader = SeekingReader(self._handle, validate_crcs=True)
            summary = self._guard(self._reader.get_summary)
            if summary is None:
                raise LogError(f"{self.path}: the MCAP file has no summary section")
        except BaseException:
            self._handle.close()
            raise
        self.summary = summary

    def __enter__(self) -> "LogFile":
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        self._handle.close()

    # --- what the summary and metadata say -------------------------------------------------------

    @property
    def channels(self) -> dict[int, Channel]:
        return self.summary.channels

    @property
    def message_counts(self) -> dict[str, int]:
        """Messages per topic."""
        counts = self.summary.statistics.channel_message_counts if self.summary.statistics else {}
        return {channel.topic: counts.get(channel_id, 0) for channel_id, channel in self.channels.items()}

    @property
    def time_span_ns(self) -> tuple[int, int]:
        statistics = self.summary.statistics
        return (statistics.message_start_time, statistics.message_end_time) if statistics else (0, 0)

    def wire_topics(self) -> list[str]:
        return sorted(channel.topic for channel in self.channels.values() if channel.message_encoding == WIRE_ENCODING)

    def metadata(self) -> dict[str, dict[str, str]]:
        return {record.name: dict(record.metadata) for record in self._guard(lambda: list(self._reader.iter_metadata()))}

    def config(self) -> Config:
        """The recorder's resolved config (the run's config with the recorder's transport flags)."""
        values = self.metadata().get(CONFIG_METADATA)
        if values is None or "toml" not in values:
            raise LogError(f"{self.path}: no {CONFIG_METADATA} metadata; not a d3rqn log")
        try:
            return from_dict(tomllib.loads(values["toml"]))
        except (tomllib.TOMLDecodeError, ConfigError) as error:
            raise LogError(f"{self.path}: the recorded config is invalid ({error})") from None

    def keys(self) -> Keys:
        config = self.config()
        return Keys(config.transport.namespace, config.run.name)

    def recorder_counters(self) -> dict[str, str]:
        """The recorder's final counters; empty for a recovered file (the recorder never closed it)."""
        return self.metadata().get(RECORDER_METADATA, {})

    # --- messages ------------------------------------------------------------------------------------

    def records(self, topics: Iterable[str] | None = None) -> Iterator[Record]:
        """Messages in log-time order, of the given topics or all."""
        iterator = self._reader.iter_messages(topics=None if topics is None else list(topics))
        while True:
            item = self._guard(lambda: next(iterator, None))
            if item is None:
                return
            schema, channel, message = item
            message_type = channel.metadata.get("message_type") or (schema.name if schema else "")
            yield Record(channel.topic, channel.message_encoding, message_type, message.data, message.log_time,
                         message.publish_time, message.sequence)

    def messages(self, *types: type[Message]) -> Iterator[tuple[Record, Message]]:
        """Decoded wire messages of the given types, in log-time order; malformed ones are skipped."""
        names = {cls.__name__ for cls in types}
        topics = [channel.topic for channel in self.channels.values()
                  if channel.message_encoding == WIRE_ENCODING and channel.metadata.get("message_type") in names]
        if not topics:
            return
        for record in self.records(topics):
            try:
                message = decode(record.data)
            except WireError:
                continue
            if isinstance(message, types):
                yield record, message

    def _guard(self, read):
        try:
            return read()
        except DAMAGED as error:
            raise LogError(f"{self.path}: damaged MCAP data ({type(error).__name__}: {error})") from None
