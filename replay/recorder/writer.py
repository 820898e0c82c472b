"""The layout of a recorded run in MCAP: one msgpack channel per key, JSON view channels, metadata.

Wire channels are named by their Zenoh key exactly (``d3rqn/<run>/episodes``), with
message encoding ``msgpack``, no schema (wire messages describe themselves) and the
message type in the channel metadata. Chunks are zstd-compressed. The recorder's
resolved config is the ``d3rqn.config`` metadata record, written and flushed first,
so even a file cut short says which run it belongs to.
"""

from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path

from mcap.well_known import SchemaEncoding
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from common.config import Config
from common.config_values import to_toml
from replay.recorder.arrival import CONFIG_METADATA, RECORDER_METADATA, WIRE_ENCODING, Arrival, Peek, publish_time_ns
from replay.recorder.views import VIEW_ENCODING, View, ViewMaker

MEGABYTE = 1 << 20
LIBRARY = f"d3rqn-log ({LIBRARY_IDENTIFIER})"


def config_metadata(config: Config) -> dict[str, str]:
    return {"toml": to_toml(config), "namespace": config.transport.namespace, "run": config.run.name}


class LogWriter:
    """Writes one log file; not thread-safe (the recorder's writer thread owns it)."""

    def __init__(self, path: Path, config: Config, views: ViewMaker | None) -> None:
        self.path = path
        self._file = open(path, "wb")
        self._mcap = Writer(self._file, chunk_size=int(config.recorder.chunk_mb * MEGABYTE),
                            compression=CompressionType.ZSTD)
        self._mcap.start(library=LIBRARY)
        self._mcap.add_metadata(CONFIG_METADATA, config_metadata(config))
        self.views = views
        self._wire_channels: dict[str, int] = {}
        self._view_channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self.messages = 0  # wire messages
        self.view_messages = 0
        self.flushed_bytes = 0  # the file's length at the last flush: whole records up to there
        self._flushed_messages = (0, 0)  # the wire and view messages up to there
        self.flush()

    @classmethod
    def open(cls, path: Path, config: Config, views: ViewMaker | None) -> LogWriter:
        """A new log at path; where even its beginning cannot be written (a full disk), no file is left."""
        try:
            return cls(path, config, views)
        except OSError:
            path.unlink(missing_ok=True)
            raise

    def write(self, arrival: Arrival, peek: Peek) -> None:
        """One wire message, then its views."""
        channel = self._wire_channels.get(arrival.key)
        if channel is None:
            channel = self._mcap.register_channel(arrival.key, WIRE_ENCODING, schema_id=0,
                                                  metadata={"message_type": peek.message_type or "unknown"})
            self._wire_channels[arrival.key] = channel
        self._mcap.add_message(channel, log_time=arrival.received_ns, data=arrival.data,
                               publish_time=publish_time_ns(arrival, peek.sender_ns), sequence=arrival.sequence)
        self.messages += 1
        if self.views is not None and self.views.wants(peek.message_type):
            for view in self.views.views(arrival.key, arrival.data, arrival.received_ns):
                self.write_view(view)

    def write_view(self, view: View) -> None:
        channel = self._view_channels.get(view.topic)
        if channel is None:
            schema = self._schemas.get(view.schema_name)
            if schema is None:
                schema = self._mcap.register_schema(view.schema_name, SchemaEncoding.JSONSchema,
                                                    json.dumps(view.schema).encode())
                self._schemas[view.schema_name] = schema
            channel = self._mcap.register_channel(view.topic, VIEW_ENCODING, schema_id=schema)
            self._view_channels[view.topic] = channel
        data = json.dumps(view.value, allow_nan=False, separators=(",", ":")).encode()
        self._mcap.add_message(channel, log_time=view.log_ns, data=data, publish_time=view.log_ns)
        self.view_messages += 1

    def add_metadata(self, name: str, values: dict[str, str]) -> None:
        self._mcap.add_metadata(name, values)

    def flush(self) -> None:
        """Closes the open chunk and hands everything to the OS: a killed process loses nothing written before."""
        self._mcap.flush()
        self.flushed_bytes, self._flushed_messages = self._file.tell(), (self.messages, self.view_messages)

    def abandon(self) -> None:
        """Closes a file that can no longer be written (a full disk) without its end, cut back to its last flush:
        it reads up to there (unfinished_ok, as a killed recorder's), and `d3rqn-log recover` makes it whole."""
        with contextlib.suppress(OSError):  # what its buffer held is what the disk refused
            self._file.close()
        os.truncate(self.path, self.flushed_bytes)
        self.messages, self.view_messages = self._flushed_messages

    def close(self, counters: dict[str, str] | None = None) -> None:
        if counters is not None:
            self._mcap.add_metadata(RECORDER_METADATA, counters)
        self._mcap.finish()
        self._file.close()
