"""What the recorder knows of one wire message on arrival, without trusting it: its type, times and version.

A log keeps the exact bytes that travelled, valid or not, so nothing here decodes a
message fully; it only peeks at the msgpack envelope of ``common.wire.envelope``.

Times (nanoseconds since the Unix epoch, as MCAP wants):

* log time: when the recorder received the sample (its own clock);
* publish time: the sender's own time field when the message has one (``time`` of
  Stats and EpisodeRecord, ``created`` of Weights); else the Zenoh
  timestamp of the sample, present when a router that forwarded it stamps samples
  (routers do by default) or the publisher did; else the reception time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import msgpack

WIRE_ENCODING = "msgpack"  # the MCAP registry's message encoding; wire messages describe themselves (no schema)
CONFIG_METADATA = "d3rqn.config"  # {"toml": the recorder's resolved config, "namespace", "run"}
RECORDER_METADATA = "d3rqn.recorder"  # the recorder's final counters, written when it closes the file
SENDER_TIME_FIELDS = ("time", "created")


class Arrival(NamedTuple):
    """One sample as received: handed from Zenoh's thread to the writer."""

    key: str
    data: bytes
    received_ns: int
    zenoh_ns: int | None  # the sample's Zenoh timestamp, if it carries one
    sequence: int  # arrival number on this key, counted before the hand-off: a gap is a dropped message


@dataclass(frozen=True)
class Peek:
    message_type: str | None  # None when the bytes are not a wire envelope
    sender_ns: int | None
    version: int | None  # Weights only


NOT_A_MESSAGE = Peek(None, None, None)


def peek(data: bytes) -> Peek:
    try:
        envelope = msgpack.unpackb(data, raw=False)
    except Exception:  # msgpack signals bad input with several exception types
        return NOT_A_MESSAGE
    if not isinstance(envelope, dict) or not isinstance(envelope.get("fields"), dict):
        return NOT_A_MESSAGE
    fields = envelope["fields"]
    message_type = envelope.get("type")
    version = fields.get("version") if message_type == "Weights" else None
    return Peek(message_type if isinstance(message_type, str) else None, _sender_ns(fields),
                version if isinstance(version, int) and not isinstance(version, bool) else None)


def _sender_ns(fields: dict) -> int | None:
    for name in SENDER_TIME_FIELDS:
        value = fields.get(name)
        if isinstance(value, float) and math.isfinite(value) and value > 0:
            return round(value * 1e9)
    return None


def publish_time_ns(arrival: Arrival, sender_ns: int | None) -> int:
    """The sender's time, else the Zenoh timestamp, else the reception time."""
    for candidate in (sender_ns, arrival.zenoh_ns):
        if candidate is not None:
            return candidate
    return arrival.received_ns


def relative_key(run_root: str, key: str) -> str:
    """The key below the run's root ('d3rqn/r/metrics/learner/0' -> 'metrics/learner/0'); other keys unchanged."""
    prefix = run_root + "/"
    return key[len(prefix):] if key.startswith(prefix) else key
