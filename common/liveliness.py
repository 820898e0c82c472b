"""Zenoh liveliness: a token per live process, and who holds one now or as it changes. A token dies with its
session, even when the process crashes, which is how roles learn that a peer is gone."""

from __future__ import annotations

import logging
from typing import Any, Callable

import zenoh

from common.logs import ThrottledLog
from common.transport import Declared, Receiver

log = logging.getLogger(__name__)


def declare_liveliness(session: zenoh.Session, key: str) -> Declared:
    """A liveliness token alive until undeclared or until the session ends (even by a crash)."""
    return Declared(key).attach(session.liveliness().declare_token(key))


def alive_keys(session: zenoh.Session, key: str, timeout_s: float) -> list[str]:
    """The keys of the liveliness tokens matching key now."""
    return sorted(str(reply.ok.key_expr) for reply in session.liveliness().get(key, timeout=timeout_s)
                  if reply.ok is not None)


def watch_liveliness(session: zenoh.Session, key: str, callback: Callable[[str, bool], Any]) -> Receiver:
    """Calls callback(token_key, alive) for tokens matching key: for those present now, then on every change."""
    warn = ThrottledLog(logger=log)
    subscription = Receiver(key)

    def on_change(sample: zenoh.Sample) -> None:
        token_key = str(sample.key_expr)
        subscription.received += 1
        try:
            callback(token_key, sample.kind == zenoh.SampleKind.PUT)
        except Exception:  # a failing callback must not raise into zenoh's thread
            subscription.failed += 1
            warn.warning("liveliness callback for %s failed", token_key, exc_info=True)

    return subscription.attach(session.liveliness().declare_subscriber(key, on_change, history=True))
