"""Encoding and decoding a message: the msgpack map ``{"schema": SCHEMA_VERSION, "type": <class name>,
"fields": {...}}``. Each field is written and checked by its codec, so ``decode`` validates everything
and any malformed input raises ``WireError``.
"""

from __future__ import annotations

import msgpack

from common.wire.codecs import Message, pack_fields, unpack_fields
from common.wire.errors import WireError
from common.wire.messages import MESSAGE_TYPES, Stats
from common.wire.metrics import STATS_SUCCESSORS, from_values

SCHEMA_VERSION = 1


def encode(message: Message) -> bytes:
    """The message as bytes; raises WireError if a field is invalid."""
    tag = type(message).__name__
    if MESSAGE_TYPES.get(tag) is not type(message):
        raise WireError(f"{tag} is not a wire message type")
    fields = pack_fields(message, tag)
    return msgpack.packb({"schema": SCHEMA_VERSION, "type": tag, "fields": fields}, use_bin_type=True)


def decode(data: bytes, expected: type[Message] | None = None) -> Message:
    """The message in data, fully checked; expected, if given, is the required type."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise WireError(f"expected bytes, got {type(data).__name__}")
    try:
        envelope = msgpack.unpackb(data, raw=False, strict_map_key=True)
    except Exception as error:  # msgpack signals bad input with several exception types
        raise WireError(f"not a msgpack message ({type(error).__name__}: {error})", "undecodable") from None
    if not isinstance(envelope, dict) or set(envelope) != {"schema", "type", "fields"}:
        raise WireError("not a wire message: expected a map with keys schema, type, fields", "undecodable")
    if type(envelope["schema"]) is not int or envelope["schema"] != SCHEMA_VERSION:
        raise WireError(f"schema version {envelope['schema']!r} is not supported (this build reads version "
                        f"{SCHEMA_VERSION})", "undecodable")
    tag = envelope["type"]
    cls = MESSAGE_TYPES.get(tag) if isinstance(tag, str) else None
    if cls is None:
        raise WireError(f"unknown message type {tag!r}", "undecodable")
    if expected is not None and cls is not expected and tag not in expected.former_types:
        raise WireError(f"expected message type {expected.__name__}, got {tag}", "wrong_type")
    message = unpack_fields(cls, envelope["fields"], cls.__name__)
    if isinstance(message, Stats) and message.source in STATS_SUCCESSORS:  # an older learner's or actor's
        message = from_values(STATS_SUCCESSORS[message.source], message.time, message.values)
    if expected is not None and type(message) is not expected:
        raise WireError(f"expected message type {expected.__name__}, got {type(message).__name__}", "wrong_type")
    return message
