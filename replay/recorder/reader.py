"""Reading a log back: a whole, sound MCAP file, or one clear LogError.

A file whose end is missing (a recorder still running, or killed before it finished)
is refused with a pointer to ``d3rqn-log recover``, unless it is opened with
``unfinished_ok``: then it is read up to its last whole record, which is what the
recorder's last flush left. The mcap library's SeekingReader needs the summary at
the end of a finished file (its NonSeekingReader would sort every message in
memory), so for an unfinished one the summary is rebuilt from the data section
(chunk headers, message indexes, metadata) and handed to the SeekingReader. A file
that ends inside a record is refused either way. Damaged data raises LogError when
it is read (chunk CRCs are checked), never a library exception.
"""

from __future__ import annotations

import struct
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import zstandard
from mcap.exceptions import McapError
from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, ChunkIndex, MetadataIndex, Schema, Statistics
from mcap.stream_reader import MAGIC_SIZE, breakup_chunk
from mcap.summary import Summary

from common.config import Config
from common.config_values import from_dict
from common.schema.fields import ConfigError
from common.keys import Keys
from common.wire.codecs import Message
from common.wire.envelope import decode
from common.wire.errors import WireError
from replay.recorder.arrival import CONFIG_METADATA, RECORDER_METADATA, WIRE_ENCODING

MCAP_MAGIC = b"\x89MCAP0\r\n"
# What the mcap library raises on damaged input: its own errors and those of struct, zstd and plain Python.
DAMAGED = (McapError, struct.error, ValueError, KeyError, IndexError, EOFError, OverflowError, zstandard.ZstdError)
RECORD_PREFIX = struct.Struct("<BQ")  # opcode, length
MESSAGE_INDEX_PREFIX = struct.Struct("<HI")  # channel id, bytes of (log time, offset) pairs
MESSAGE_INDEX_ENTRY_BYTES = 16


class LogError(Exception):
    """A log cannot be read; the message is one line naming the file and the fault."""


@dataclass(frozen=True)
class Record:
    topic: str
    encoding: str  # "msgpack" for wire messages, "json" for views
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


def whole_records_end(handle, size: int) -> int:
    """The offset just past the last record that lies entirely in the file (records follow the magic)."""
    position = MAGIC_SIZE
    while position + RECORD_PREFIX.size <= size:
        handle.seek(position)
        _, length = RECORD_PREFIX.unpack(handle.read(RECORD_PREFIX.size))
        if position + RECORD_PREFIX.size + length > size:
            break
        position += RECORD_PREFIX.size + length
    return position


class LogFile:
    """An open log; use as a context manager. With unfinished_ok, a file without its end (a recorder
    still writing it, or killed) is read up to its last whole record; `finished` says which it was."""

    def __init__(self, path: str | Path, unfinished_ok: bool = False) -> None:
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
            tail = self._handle.read(MAGIC_SIZE)
            self.finished = tail == MCAP_MAGIC
            if not (unfinished_ok and head == MCAP_MAGIC and not self.finished):
                check_ends(self.path, head, tail)
            summary = None if self.finished else self._guard(self._scan_summary)
            self._handle.seek(0)
            self._reader = _Reader(self._handle, summary)
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
        names = {name for cls in types for name in (cls.__name__, *cls.former_types)}
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

    # --- an unfinished file ------------------------------------------------------------------------

    def _scan_summary(self) -> Summary:
        """The summary a finished file would end with, from the records of the data section."""
        handle, size = self._handle, self.size_bytes
        if whole_records_end(handle, size) != size:
            raise LogError(f"{self.path}: unfinished, and it ends inside a record (truncated, or caught in the "
                           f"middle of a write: try again); `d3rqn-log recover {self.path} FIXED.mcap` rewrites the "
                           f"whole records before the cut")
        summary = Summary()
        counts: dict[int, int] = {}
        position = MAGIC_SIZE
        while position < size:
            handle.seek(position)
            opcode, length = RECORD_PREFIX.unpack(handle.read(RECORD_PREFIX.size))
            body = position + RECORD_PREFIX.size
            if opcode == Opcode.DATA_END:
                break  # a summary was being written: what follows is not data
            if opcode == Opcode.CHUNK:
                summary.chunk_indexes.append(_chunk_index(handle, position, RECORD_PREFIX.size + length))
            elif opcode == Opcode.MESSAGE_INDEX and summary.chunk_indexes:  # these follow their chunk
                channel_id, entry_bytes = MESSAGE_INDEX_PREFIX.unpack(handle.read(MESSAGE_INDEX_PREFIX.size))
                chunk = summary.chunk_indexes[-1]
                chunk.message_index_offsets[channel_id] = position
                chunk.message_index_length = body + length - next(iter(chunk.message_index_offsets.values()))
                counts[channel_id] = counts.get(channel_id, 0) + entry_bytes // MESSAGE_INDEX_ENTRY_BYTES
            elif opcode == Opcode.METADATA:
                name = handle.read(struct.unpack("<I", handle.read(4))[0]).decode()
                summary.metadata_indexes.append(MetadataIndex(position, RECORD_PREFIX.size + length, name))
            # the recorder writes every schema, channel and message inside a chunk
            position = body + length
        self._add_channels(summary, counts)
        chunks = summary.chunk_indexes
        summary.statistics = Statistics(
            message_count=sum(counts.values()), schema_count=len(summary.schemas),
            channel_count=len(summary.channels), attachment_count=0, metadata_count=len(summary.metadata_indexes),
            chunk_count=len(chunks), channel_message_counts=counts,
            message_start_time=min((chunk.message_start_time for chunk in chunks), default=0),
            message_end_time=max((chunk.message_end_time for chunk in chunks), default=0))
        return summary

    def _add_channels(self, summary: Summary, counts: dict[int, int]) -> None:
        """Schemas and channels from the chunks whose message indexes name a channel not seen before: a
        channel is defined in the chunk of its first message, or in the one before if that filled up just
        then; the other chunks are decompressed only when a channel is still missing."""
        def read(chunk_index: ChunkIndex) -> None:
            self._handle.seek(chunk_index.chunk_start_offset + RECORD_PREFIX.size)
            for record in breakup_chunk(Chunk.read(ReadDataStream(self._handle)), validate_crc=True):
                if isinstance(record, Schema):
                    summary.schemas[record.id] = record
                elif isinstance(record, Channel):
                    summary.channels[record.id] = record

        for chunk_index in summary.chunk_indexes:
            if not chunk_index.message_index_offsets.keys() <= summary.channels.keys():
                read(chunk_index)
        if not counts.keys() <= summary.channels.keys():
            for chunk_index in summary.chunk_indexes:
                read(chunk_index)
        if not counts.keys() <= summary.channels.keys():
            raise LogError(f"{self.path}: messages of channels {sorted(counts.keys() - summary.channels.keys())} "
                           f"that no whole chunk defines")

    def _guard(self, read):
        try:
            return read()
        except DAMAGED as error:
            raise LogError(f"{self.path}: damaged MCAP data ({type(error).__name__}: {error})") from None


class _Reader(SeekingReader):
    """The library's SeekingReader, with the summary rebuilt for an unfinished file (None: read the file's own)."""

    def __init__(self, handle, summary: Summary | None) -> None:
        super().__init__(handle, validate_crcs=True)
        self._rebuilt = summary

    def get_summary(self) -> Summary | None:
        return self._rebuilt if self._rebuilt is not None else super().get_summary()


def _chunk_index(handle, offset: int, length: int) -> ChunkIndex:
    """The index entry of the chunk record at offset, from its header (its records are not read)."""
    start, end, uncompressed_size, _crc, compression_length = struct.unpack("<QQQII", handle.read(32))
    compression = handle.read(compression_length).decode()
    (compressed_size,) = struct.unpack("<Q", handle.read(8))
    return ChunkIndex(message_start_time=start, message_end_time=end, chunk_start_offset=offset, chunk_length=length,
                      message_index_offsets={}, message_index_length=0, compression=compression,
                      compressed_size=compressed_size, uncompressed_size=uncompressed_size)
