"""Rewriting a cut-short log (a recorder killed, a disk full) into a complete, indexed MCAP file.

The source is read record by record up to the last record that is whole; a chunk
whose CRC or compression is broken is skipped and counted, and so are messages
whose channel was defined in such a chunk. Schemas, channels, messages (with
their times and sequence numbers) and metadata are copied into a new file that
has a summary, indexes and a footer.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from mcap.exceptions import EndOfFile
from mcap.records import Attachment, Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import MAGIC_SIZE, StreamReader, breakup_chunk
from mcap.writer import Writer

from replay.recorder.reader import DAMAGED, MCAP_MAGIC, LogError, whole_records_end


@dataclass
class Recovery:
    messages: int = 0
    channels: int = 0
    metadata: int = 0
    chunks_skipped: int = 0
    messages_orphaned: int = 0  # their channel record was lost with a skipped chunk
    bytes_read: int = 0  # the whole records of the source; the rest was a cut-off record
    source_bytes: int = 0
    damage: str = ""  # what stopped the copy before the end of the whole records, if anything


class _Prefix:
    """A file read only up to `end`, so the stream stops cleanly after the last whole record."""

    def __init__(self, handle, end: int) -> None:
        self._handle = handle
        self._end = end

    def read(self, size: int) -> bytes:
        size = min(size, self._end - self._handle.tell())
        return self._handle.read(size) if size > 0 else b""


def recover(source: str | Path, target: str | Path) -> Recovery:
    source, target = Path(source), Path(target)
    if source.resolve() == target.resolve():
        raise LogError(f"{target}: recover writes a new file; choose another name than the source")
    try:
        handle = open(source, "rb")
    except OSError as error:
        raise LogError(f"{source}: cannot open ({error.strerror})") from None
    partial = target.with_name(target.name + ".partial")
    try:
        with handle, open(partial, "wb") as output:
            if handle.read(MAGIC_SIZE) != MCAP_MAGIC:
                raise LogError("not an MCAP file (it does not start with the MCAP magic)")
            size = handle.seek(0, 2)
            end = whole_records_end(handle, size)
            handle.seek(MAGIC_SIZE)
            result = Recovery(bytes_read=end, source_bytes=size)
            _copy(StreamReader(_Prefix(handle, end), skip_magic=True, emit_chunks=True), Writer(output), result)
    except LogError as error:
        partial.unlink(missing_ok=True)
        raise LogError(f"{source}: {error}") from None
    os.replace(partial, target)
    return result


def _copy(reader: StreamReader, writer: Writer, result: Recovery) -> None:
    schemas: dict[int, int] = {0: 0}  # source id -> target id
    channels: dict[int, int] = {}
    started = False
    records = reader.records
    while True:
        try:
            record = next(records)
        except (StopIteration, EndOfFile):
            break
        except DAMAGED as error:  # keep what came before the damage
            result.damage = f"{type(error).__name__}: {error}"
            break
        if isinstance(record, Header):
            writer.start(record.profile, record.library)
            started = True
            continue
        if not started:
            raise LogError("the MCAP file has no header record")
        if isinstance(record, (DataEnd, Footer)):
            break  # a finished file: the summary that follows is rebuilt by the writer
        for inner in _unpack(record, result):
            _copy_record(inner, writer, schemas, channels, result)
    if not started:
        raise LogError("the MCAP file holds no whole record")
    writer.finish()


def _unpack(record, result: Recovery) -> list:
    if not isinstance(record, Chunk):
        return [record]
    try:
        return breakup_chunk(record, validate_crc=True)
    except DAMAGED:
        result.chunks_skipped += 1
        return []


def _copy_record(record, writer: Writer, schemas: dict[int, int], channels: dict[int, int],
                 result: Recovery) -> None:
    if isinstance(record, Schema) and record.id not in schemas:
        schemas[record.id] = writer.register_schema(record.name, record.encoding, record.data)
    elif isinstance(record, Channel) and record.id not in channels:
        if record.schema_id not in schemas:
            return
        channels[record.id] = writer.register_channel(record.topic, record.message_encoding,
                                                      schemas[record.schema_id], dict(record.metadata))
        result.channels += 1
    elif isinstance(record, Message):
        if record.channel_id not in channels:
            result.messages_orphaned += 1
            return
        writer.add_message(channels[record.channel_id], record.log_time, record.data, record.publish_time,
                           record.sequence)
        result.messages += 1
    elif isinstance(record, Metadata):
        writer.add_metadata(record.name, dict(record.metadata))
        result.metadata += 1
    elif isinstance(record, Attachment):
        writer.add_attachment(record.create_time, record.log_time, record.name, record.media_type, record.data)
