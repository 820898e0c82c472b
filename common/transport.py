"""Zenoh in one place: the session, and typed put/subscribe/query helpers (the key names are
common/keys.py, the shared-memory pool common/shared_memory.py, the liveliness tokens common/liveliness.py).

Roles never touch payload bytes: what goes out is encoded with ``common.wire.envelope``
and what comes in is decoded and checked. Malformed input is logged (rate-limited)
and counted, and never raises into Zenoh's threads, so a bad sender cannot stop
a service.

Callbacks run on Zenoh's threads: keep them short, and guard shared state with a lock.
Large messages (a ~50 MB Weights) are sent with blocking congestion control, so they are
never dropped under load; Zenoh fragments them over the link. A publisher given a
``SharedMemory`` puts them from Zenoh shared memory instead (``transport.shared_memory``):
subscribers on the same host map the buffer, the others get it over the network as before.

    with open_session(config.transport) as session:
        keys = Keys(config.transport.namespace, config.run.name)
        episodes = subscribe(session, keys.episodes, on_episode)
        ...
"""

from __future__ import annotations

import json
import logging
import os
import socket
import threading
import time
from pathlib import Path
from typing import Any, Callable

import zenoh

from common.access import acl_config
from common.config import TransportConfig
from common.logs import ThrottledLog
from common.shared_memory import SharedMemory
from common.wire.codecs import Message
from common.wire.envelope import decode, encode
from common.wire.errors import WireError

log = logging.getLogger(__name__)

LOOPBACK = "127.0.0.1"


# --- session ---------------------------------------------------------------------------

def zenoh_config(config: TransportConfig) -> zenoh.Config:
    """The zenoh.Config for a TransportConfig: mode, endpoints, scouting, TLS and access
    control, nothing implicit.

    An empty ``listen`` means no listener at all (an actor that only connects): in
    peer mode it still reaches every listening peer it learns of through gossip.
    """
    zconfig = zenoh.Config()
    zconfig.insert_json5("mode", json.dumps(config.mode))
    zconfig.insert_json5("listen/endpoints", json.dumps(list(config.listen)))
    zconfig.insert_json5("connect/endpoints", json.dumps(list(config.connect)))
    zconfig.insert_json5("scouting/multicast/enabled", json.dumps(config.multicast_scouting))
    zconfig.insert_json5("transport/shared_memory/enabled", json.dumps(config.shared_memory))
    if config.mode == "client":
        # A client fails at once by default when its router is not up yet; retry for a while instead.
        zconfig.insert_json5("connect/timeout_ms", json.dumps(round(config.connect_timeout_s * 1000)))
    tls = tls_settings(config)
    if tls:
        zconfig.insert_json5("transport/link/tls", json.dumps(tls))
    if config.acl:
        zconfig.insert_json5("access_control", json.dumps(acl_config(config.namespace, {
            "learner": config.acl_learners, "actor": config.acl_actors, "replay": config.acl_replays,
            "observer": config.acl_observers})))
    return zconfig


def tls_settings(config: TransportConfig) -> dict[str, Any]:
    """Zenoh's transport/link/tls block (empty without TLS options); each named file must exist.

    The certificate and key serve listening and, with mutual TLS, connecting too: Zenoh
    presents a client certificate only when enable_mtls is set on the connecting side.
    """
    files = {"tls_ca": config.tls_ca, "tls_certificate": config.tls_certificate, "tls_key": config.tls_key}
    if not any(files.values()) and not config.tls_mtls:
        return {}
    for key, path in files.items():
        if path and not Path(path).is_file():
            raise FileNotFoundError(f"transport.{key}: no file {path!r} (from {Path.cwd()})")
    tls: dict[str, Any] = {"enable_mtls": config.tls_mtls, "verify_name_on_connect": config.tls_verify_name}
    if config.tls_ca:
        tls["root_ca_certificate"] = str(Path(config.tls_ca).resolve())
    if config.tls_certificate:
        certificate, key = str(Path(config.tls_certificate).resolve()), str(Path(config.tls_key).resolve())
        tls.update(listen_certificate=certificate, listen_private_key=key)
        if config.tls_mtls:
            tls.update(connect_certificate=certificate, connect_private_key=key)
    return tls


def open_session(config: TransportConfig) -> zenoh.Session:
    """Opens a session; use it as a context manager (``with open_session(cfg) as session``) or close it."""
    _zenoh_errors_to_log()
    return zenoh.open(zenoh_config(config))


def _zenoh_errors_to_log() -> None:
    """Zenoh's own errors (RUST_LOG's level where set) on stdout, so into the process's log: a transport
    it closes as unresponsive ("Unable to push non droppable network message") says so there."""
    os.environ.setdefault("NO_COLOR", "1")  # plain lines in the log files
    zenoh.init_log_from_env_or("error")


def free_port() -> int:
    """A TCP port free on the loopback interface now (for a local run or a test; not reserved)."""
    with socket.socket() as probe:
        probe.bind((LOOPBACK, 0))
        return probe.getsockname()[1]


def loopback_endpoint(port: int | None = None) -> str:
    """A Zenoh endpoint on the loopback interface: the given port, or a free one."""
    return f"tcp/{LOOPBACK}:{port or free_port()}"


# --- logging and closing ---------------------------------------------------------------------

class Declared:
    """A declared zenoh entity on one key; undeclare() works once, also after the session closed."""

    def __init__(self, key: str) -> None:
        self.key = key
        self._entity: Any = None

    def attach(self, entity: Any):
        """Holds the zenoh entity; separate from __init__ so callbacks can see this object before declaring."""
        self._entity = entity
        return self

    def undeclare(self) -> None:
        entity, self._entity = self._entity, None
        if entity is not None:
            entity.undeclare()

    def __enter__(self):
        return self

    def __exit__(self, *exc_info) -> None:
        self.undeclare()


# --- publish / subscribe ----------------------------------------------------------------------

class Publisher(Declared):
    """Puts wire messages on one key, from shared memory when given one."""

    def __init__(self, key: str, shared_memory: SharedMemory | None = None) -> None:
        super().__init__(key)
        self.shared_memory = shared_memory

    def put(self, message: Message) -> int:
        """Encodes and sends the message; returns the encoded size in bytes."""
        data = encode(message)
        self._entity.put(data if self.shared_memory is None else self.shared_memory.payload(data))
        return len(data)

    @property
    def matched(self) -> bool:
        """Whether a subscriber is known for the key; a put with none is lost, so a sender can wait for one."""
        return self._entity.matching_status.matching  # a MatchingStatus object, whatever the stubs say


def publisher(session: zenoh.Session, key: str, *, reliable: bool = True, express: bool = False,
              shared_memory: SharedMemory | None = None) -> Publisher:
    """A publisher on key. reliable: block when the link is congested instead of dropping
    (use False for frequent, replaceable data); express: send at once without batching;
    shared_memory: put every message from it (large, infrequent ones: weights)."""
    congestion = zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
    entity = session.declare_publisher(key, congestion_control=congestion, express=express)
    return Publisher(key, shared_memory).attach(entity)


def put_once(session: zenoh.Session, key: str, message: Message) -> int:
    """Encodes and sends one message on a key that has no declared publisher (keys with an id in them);
    reliable (blocks while congested). Returns the encoded size in bytes."""
    data = encode(message)
    session.put(key, data, congestion_control=zenoh.CongestionControl.BLOCK)
    return len(data)


class Receiver(Declared):
    """A subscriber or queryable with counters: received (handed to the callback), rejected
    (malformed input), failed (the callback raised), shared (samples that came in shared memory)."""

    def __init__(self, key: str) -> None:
        super().__init__(key)
        self.received = 0
        self.rejected = 0
        self.failed = 0
        self.shared = 0


def subscribe(session: zenoh.Session, key: str, callback: Callable[[Message, str], Any], *,
              expected: type[Message] | None = None, max_bytes: int | None = None) -> Receiver:
    """Calls callback(message, sample_key) for each decoded sample on key.

    Samples that are not a valid message (of type expected, if given; at most
    max_bytes long, if given) are logged and counted in ``rejected``.
    """
    warn = ThrottledLog(logger=log)
    subscription = Receiver(key)

    def on_sample(sample: zenoh.Sample) -> None:
        sample_key = str(sample.key_expr)
        subscription.shared += _in_shared_memory(sample.payload)
        message = _decode_sample(sample, expected, max_bytes)
        if isinstance(message, str):
            subscription.rejected += 1
            warn.warning("rejected a sample on %s: %s", sample_key, message)
            return
        subscription.received += 1
        try:
            callback(message, sample_key)
        except Exception:  # a failing callback must not raise into zenoh's thread
            subscription.failed += 1
            warn.warning("callback for %s failed on a %s", sample_key, type(message).__name__, exc_info=True)

    return subscription.attach(session.declare_subscriber(key, on_sample))


def _in_shared_memory(payload: zenoh.ZBytes) -> bool:
    try:
        return payload.as_shm() is not None
    except Exception:  # a zenoh built without shared memory
        return False


def _decode_sample(sample: zenoh.Sample, expected: type[Message] | None, max_bytes: int | None) -> Message | str:
    """The message of a sample, or the reason it is refused."""
    if sample.kind != zenoh.SampleKind.PUT:
        return f"a {sample.kind} sample carries no message"
    size = len(sample.payload)
    if max_bytes is not None and size > max_bytes:
        return f"{size} bytes exceed the limit of {max_bytes}"
    try:
        return decode(sample.payload.to_bytes(), expected)
    except WireError as error:
        return str(error)


# --- query / reply ---------------------------------------------------------------------------

def serve(session: zenoh.Session, key: str, handler: Callable[[Message | None], Message | None], *,
          expected: type[Message] | None = None) -> Receiver:
    """Answers queries on key with handler(request) -> reply message, or None for no reply.

    A query without payload gives handler(None). A malformed request or a handler
    error is logged, counted, and answered with an error reply; the service goes on.
    """
    warn = ThrottledLog(logger=log)
    service = Receiver(key)

    def on_query(query: zenoh.Query) -> None:
        with query:  # finalises the query on exit, so the requester is not left waiting
            answer = answer_of(query)
            try:
                if isinstance(answer, bytes):
                    query.reply(key, answer)
                elif isinstance(answer, str):
                    query.reply_err(answer)
            except zenoh.ZError as error:
                warn.warning("could not reply on %s: %s", key, error)

    def answer_of(query: zenoh.Query) -> bytes | str | None:
        """The encoded reply, an error text, or None for no reply."""
        try:
            request_message = _request_of(query, expected)
        except WireError as error:
            service.rejected += 1
            warn.warning("rejected a request on %s: %s", key, error)
            return f"bad request: {error}"
        try:
            reply = handler(request_message)
            service.received += 1
            return None if reply is None else encode(reply)
        except Exception as error:  # a failing handler answers with an error instead of crashing the service
            service.failed += 1
            warn.warning("handler for %s failed", key, exc_info=True)
            return f"handler failed: {type(error).__name__}: {error}"

    return service.attach(session.declare_queryable(key, on_query))


def _request_of(query: zenoh.Query, expected: type[Message] | None) -> Message | None:
    """The query's decoded payload, None without one; WireError if it is malformed."""
    payload = query.payload
    return None if payload is None or len(payload) == 0 else decode(payload.to_bytes(), expected)


class PendingQuery:
    """A decoded query whose answer may come later, from any thread; answered once.

    ``reply(message)`` sends the answer, ``drop()`` ends the query without one (the
    requester's get returns no reply); either finalises the query, later calls do nothing.
    """

    def __init__(self, query: zenoh.Query, key: str, request: Message | None, warn: ThrottledLog) -> None:
        self.request = request
        self.received = time.monotonic()
        self._query: zenoh.Query | None = query
        self._key = key
        self._warn = warn
        self._lock = threading.Lock()

    @property
    def answered(self) -> bool:
        return self._query is None

    def reply(self, message: Message) -> bool:
        """Encodes and sends message; False if the query was already answered or the reply failed."""
        data = encode(message)
        return self._finish(lambda query: query.reply(self._key, data))

    def reply_error(self, text: str) -> bool:
        return self._finish(lambda query: query.reply_err(text))

    def drop(self) -> None:
        self._finish(None)

    def _finish(self, send) -> bool:
        with self._lock:
            query, self._query = self._query, None
        if query is None:
            return False
        try:
            if send is not None:
                send(query)
            return True
        except zenoh.ZError as error:
            self._warn.warning("could not reply on %s: %s", self._key, error)
            return False
        finally:
            query.drop()


def serve_deferred(session: zenoh.Session, key: str, on_query: Callable[[PendingQuery], Any], *,
                   expected: type[Message] | None = None) -> Receiver:
    """Hands each query on key to on_query as a PendingQuery, which must be answered or dropped
    later (a service that holds replies back, answering from its own thread).

    on_query runs on zenoh's thread: it must only park the query, never wait. A malformed
    request is logged, counted and answered with an error at once; so is an on_query that raises.
    """
    warn = ThrottledLog(logger=log)
    service = Receiver(key)

    def on_zenoh_query(query: zenoh.Query) -> None:
        try:
            request_message = _request_of(query, expected)
        except WireError as error:
            service.rejected += 1
            warn.warning("rejected a request on %s: %s", key, error)
            PendingQuery(query, key, None, warn).reply_error(f"bad request: {error}")
            return
        pending = PendingQuery(query, key, request_message, warn)
        try:
            on_query(pending)
            service.received += 1
        except Exception as error:  # a failing handler answers with an error instead of crashing the service
            service.failed += 1
            warn.warning("handler for %s failed", key, exc_info=True)
            pending.reply_error(f"handler failed: {type(error).__name__}: {error}")

    return service.attach(session.declare_queryable(key, on_zenoh_query))


def request(session: zenoh.Session, key: str, message: Message | None, timeout_s: float, *,
            expected: type[Message] | None = None) -> Message | None:
    """Sends message (or no payload for None) as a query; returns the first valid reply,
    or None when there is no queryable, only error replies, a malformed reply, or the timeout passes."""
    payload = None if message is None else encode(message)
    replies = session.get(key, payload=payload, timeout=timeout_s,
                          congestion_control=zenoh.CongestionControl.BLOCK,  # the reply travels with the query's QoS
                          consolidation=zenoh.ConsolidationMode.NONE)  # deliver the first reply without waiting for others
    for reply in replies:
        if reply.ok is None:
            log.warning("error reply on %s: %s", key, reply.err.payload.to_bytes().decode("utf-8", "replace"))
            continue
        try:
            return decode(reply.ok.payload.to_bytes(), expected)
        except WireError as error:
            log.warning("malformed reply on %s: %s", key, error)
            return None
    return None
