"""Finished episodes on their way to the replay, held until the replay says it keeps them.

The driving loop offers episodes and waits while too many wait to be sent (a count and a
byte size). One sender thread (`Outbox.run`) publishes them, oldest first, while a replay
listens. A sent episode stays in flight until the replay's EpisodeAck (replay/acks.py)
says kept or refused. It is sent again when:

- the replay has not said received within `resend_after_s` (lost in transit or in a partition);
- received but not kept within `keep_within_s` (the word was lost);
- a replay comes back after none was listening (one restarted from its snapshot lacks
  what it received after that snapshot).

The replay's ledger takes no episode twice, so sending again is safe. In-flight episodes
are bounded by a byte size: past it the oldest is given up, counted as released.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass

from common.logs import Every
from common.wire.messages import Episode, EpisodeAck

log = logging.getLogger(__name__)

MEGABYTE = 1 << 20
REPLAY_WAIT_LOG_S = 30.0  # the "waiting for a replay" warnings, at most this often


@dataclass
class Flight:
    episode: Episode
    size: int
    sent_at: float
    received: bool = False
    sends: int = 0  # successful sends


def episode_bytes(episode: Episode) -> int:
    return episode.observations.nbytes + episode.actions.nbytes * 3


class Outbox:
    def __init__(self, max_episodes: int, max_bytes: int, *, incarnation: int = 0, actor_id: int = 0,
                 resend_after_s: float = 5.0, keep_within_s: float = 65.0, max_in_flight_bytes: int = 256 * MEGABYTE,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.max_episodes, self.max_bytes = max_episodes, max_bytes
        self.actor_id, self.incarnation = actor_id, incarnation
        self.resend_after_s, self.keep_within_s = resend_after_s, keep_within_s
        self.max_in_flight_bytes = max_in_flight_bytes
        self.clock = clock
        self._queue: deque[tuple[Episode, int]] = deque()
        self._bytes = 0
        self._flights: OrderedDict[int, Flight] = OrderedDict()  # by episode index, oldest first
        self._flight_bytes = 0
        self._changed = threading.Condition()
        self._replay_was_gone = False
        self.sent = 0  # episodes sent at least once
        self.resent = 0  # sends beyond the first
        self.kept = 0
        self.refused = 0
        self.released = 0  # in flight, given up over max_in_flight_bytes
        self.dropped = 0  # given up unsent: the actor stopped
        self.send_failures = 0  # sends that raised (the episode stays in flight)
        self.foreign_acks = 0  # words on another actor's or an earlier incarnation's episodes

    def __len__(self) -> int:
        with self._changed:
            return len(self._queue)

    @property
    def in_flight(self) -> int:
        with self._changed:
            return len(self._flights)

    def offer(self, episode: Episode, stop: threading.Event) -> bool:
        """Queues the episode once there is room; False if stopped first (the episode is dropped)."""
        size = episode_bytes(episode)
        waiting = Every(REPLAY_WAIT_LOG_S)
        with self._changed:
            while self._queue and (len(self._queue) >= self.max_episodes or self._bytes + size > self.max_bytes):
                if stop.is_set():
                    self.dropped += 1
                    return False
                if waiting.due():
                    log.warning("%d finished episodes (%.1f MB) wait for a replay: holding the next episode",
                                len(self._queue), self._bytes / MEGABYTE)
                self._changed.wait(0.1)
            self._queue.append((episode, size))
            self._bytes += size
            self._changed.notify_all()
        return True

    def run(self, send: Callable[[Episode], object], listening: Callable[[], bool], stop: threading.Event) -> None:
        """Sends what is due (episodes to send again first, oldest first) while a replay listens; until stop."""
        waiting = Every(REPLAY_WAIT_LOG_S)
        while not stop.is_set():
            if not listening():
                with self._changed:
                    self._replay_was_gone = True
                    queued = len(self._queue) + len(self._flights)
                if queued and waiting.due():
                    log.warning("no replay listens; %d finished episodes wait (%d sent, not yet kept)", queued,
                                len(self._flights))
                stop.wait(0.1)
                continue
            due = self._next_due()
            if due is None:
                with self._changed:
                    self._changed.wait(0.1)
                continue
            self._send(send, *due)

    def _next_due(self) -> tuple[Episode, int, Flight | None] | None:
        with self._changed:
            now = self.clock()
            if self._replay_was_gone:  # a replay is back: it may lack what the last one received
                self._replay_was_gone = False
                for flight in self._flights.values():
                    flight.sent_at, flight.received = -float("inf"), False
            for flight in self._flights.values():
                wait = self.keep_within_s if flight.received else self.resend_after_s
                if now - flight.sent_at >= wait:
                    return flight.episode, flight.size, flight
            if self._queue:
                episode, size = self._queue[0]
                return episode, size, None
            return None

    def _send(self, send, episode: Episode, size: int, flight: Flight | None) -> None:
        with self._changed:  # in flight before it goes: a word may come back before send returns
            if flight is None:
                self._queue.popleft()
                self._bytes -= size
                flight = self._take_off(episode, size)
            flight.sent_at, flight.received = self.clock(), False
        try:
            send(episode)
        except Exception as error:  # it stays in flight and is tried again; the others must go on
            with self._changed:
                self.send_failures += 1
            log.warning("could not send episode %d: %s; will try again", episode.episode_index, error)
            return
        with self._changed:
            self.sent += flight.sends == 0
            self.resent += flight.sends > 0
            flight.sends += 1
            self._changed.notify_all()

    def _take_off(self, episode: Episode, size: int) -> Flight:
        flight = self._flights[episode.episode_index] = Flight(episode, size, self.clock())
        self._flight_bytes += size
        while self._flight_bytes > self.max_in_flight_bytes and len(self._flights) > 1:
            _, oldest = self._flights.popitem(last=False)
            self._flight_bytes -= oldest.size
            self.released += 1
            if self.released in (1, 10, 100) or self.released % 1000 == 0:
                log.warning("%d sent episodes given up before the replay said it keeps them (actor.in_flight_mb "
                            "%.0f is full: is the replay too old to acknowledge?)", self.released,
                            self.max_in_flight_bytes / MEGABYTE)
        return flight

    def on_ack(self, ack: EpisodeAck, key: str = "") -> None:
        """The replay's word on this actor's episodes (a Zenoh callback: never waits)."""
        if not isinstance(ack, EpisodeAck) or (ack.actor_id, ack.incarnation) != (self.actor_id, self.incarnation):
            with self._changed:
                self.foreign_acks += 1
            return
        with self._changed:
            for word, done in (("kept", True), ("refused", True), ("received", False)):
                for index in getattr(ack, word).tolist():
                    flight = self._flights.get(index)
                    if flight is None:
                        continue
                    if done:
                        del self._flights[index]
                        self._flight_bytes -= flight.size
                        self.kept += word == "kept"
                        self.refused += word == "refused"
                    else:
                        flight.received = True
            self._changed.notify_all()

    def drain(self, stop: threading.Event) -> None:
        """Waits until every queued episode is sent and received by the replay, or stop."""
        with self._changed:
            while (self._queue or any(not flight.received for flight in self._flights.values())) \
                    and not stop.is_set():
                self._changed.wait(0.1)

    def drop_rest(self) -> int:
        """Gives up the unsent episodes (counted as dropped); returns how many."""
        with self._changed:
            count = len(self._queue)
            self._queue.clear()
            self._bytes = 0
            self.dropped += count
            return count

    def values(self) -> dict[str, int]:
        """The counters, for the actor's stats."""
        with self._changed:
            return {"episodes_sent": self.sent, "episodes_resent": self.resent, "episodes_kept": self.kept,
                    "episodes_refused": self.refused, "episodes_released": self.released,
                    "episodes_dropped": self.dropped, "episode_send_failures": self.send_failures,
                    "episodes_queued": len(self._queue),
                    "episodes_in_flight": len(self._flights), "acks_foreign": self.foreign_acks}
