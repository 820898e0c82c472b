"""A role's link to the hub: what it declares on its Zenoh session, declared again on a fresh session when
the replay's word stops coming.

A Zenoh session can stay half-alive. In the network-fault lab, on an overloaded machine, a client actor's
episodes still reached the replay for minutes while no weights, acks or rate words reached it; it never
held, and outran the rate limiter. A client learner's batch requests reached the replay, which served
them, while no batch and no stats word came back for three minutes, until the replay restarted. The
replay announces its word at least every replay.stats_period_s. After a role's silence_reopen_s without
it, and again after each further span, keep_hearing() replaces the session (Shell.reopen) and HubLink
declares everything again on the new one (the actor also holds its next episode after
actor.silence_hold_s, actor/mailbox.py).
"""

from __future__ import annotations

import logging
import threading
from typing import Any, Callable

import zenoh

from common.shell import Shell
from common.transport import Publisher, Receiver

log = logging.getLogger("hub_link")

Declare = Callable[[zenoh.Session], tuple[dict[str, Receiver], dict[str, Publisher]]]


class HubLink:
    """The session in use, with its receivers and publishers by name; `declare` makes them on a session."""

    def __init__(self, shell: Shell, session: zenoh.Session, declare: Declare) -> None:
        self._shell = shell
        self.role = shell.role
        self._declare = declare
        self._lock = threading.Lock()
        self._rejected_before: dict[str, int] = {}  # receivers of sessions given up
        self.reopened = 0
        self.session, self.receivers, self.publishers = session, *declare(session)

    def put(self, name: str, message: Any) -> None:
        """Publishes on the current session, on the fresh one where a reopen closed it meanwhile; raises
        where that fails too (the caller counts a failed send)."""
        with self._lock:
            out = self.publishers[name]
        try:
            out.put(message)
        except Exception:
            with self._lock:
                fresh = self.publishers[name]
            if fresh is out:
                raise
            fresh.put(message)

    def matched(self, name: str) -> bool:
        with self._lock:
            out = self.publishers[name]
        try:
            return out.matched
        except Exception:  # noqa: BLE001 - undeclared by a reopen in between: none known
            return False

    def rejected(self) -> dict[str, int]:
        """Messages each door refused, over every session this process has had."""
        with self._lock:
            return self._rejected_so_far()

    def reopen(self) -> bool:
        """A fresh session with everything declared again; False where none opened (the old one stays)."""
        return self._shell.reopen(self._take)

    def _take(self, session: zenoh.Session) -> None:
        """Declares on a fresh session and uses it from now on; what was declared on the old one goes."""
        receivers, publishers = self._declare(session)
        with self._lock:
            stale = self._declared()
            self._rejected_before = self._rejected_so_far()
            self.session, self.receivers, self.publishers = session, receivers, publishers
            self.reopened += 1
        for entity in stale:
            _undeclare_quietly(entity)

    def _rejected_so_far(self) -> dict[str, int]:
        return {door: self._rejected_before.get(door, 0) + receiver.rejected
                for door, receiver in self.receivers.items()}

    def _declared(self) -> list:
        return [*self.receivers.values(), *self.publishers.values()]

    def close(self) -> None:
        with self._lock:
            entities = self._declared()
        for entity in entities:
            _undeclare_quietly(entity)


def _undeclare_quietly(entity) -> None:
    try:
        entity.undeclare()
    except Exception as error:  # noqa: BLE001 - a session given up may refuse; it closes anyway
        log.debug("undeclaring %s: %s", entity.key, error)


def keep_hearing(link: HubLink, silent_s: Callable[[], float], reopen_after_s: float, stop: threading.Event,
                 poll_s: float = 1.0) -> None:
    """Reopens the link's session once silent_s() (seconds without the replay's word) reaches reopen_after_s,
    and again at each further multiple of it; until stop."""
    due = reopen_after_s
    while not stop.wait(poll_s):
        silence = silent_s()
        if silence < reopen_after_s:
            due = reopen_after_s
            continue
        if silence < due:
            continue
        due += reopen_after_s
        log.warning("no word from the replay for %.0f s: this %s may no longer hear the hub; reopening its Zenoh "
                    "session (reopened %d time(s) before)", silence, link.role, link.reopened)
        if link.reopen():
            log.info("Zenoh session reopened; everything declared again on it")
