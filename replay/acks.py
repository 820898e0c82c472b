"""The replay's word to each actor on its episodes, by name (actor_id, incarnation, episode_index).

An actor keeps every episode it sent until the replay says it keeps it (actor/delivery.py),
so an episode lost in transit, in a partition, or with a replay that died before its
snapshot is sent again, and the ledger (replay/ledger.py) takes none twice. The words:

- received: taken into the store (or a duplicate of one not yet in a snapshot);
- kept: durable. With snapshots on, that is once a snapshot holding the episode is on disk
  (a duplicate of an episode already in one is kept at once); with snapshots off, on receipt;
- refused: never taken (malformed, or the run is closed).

Pure and thread-safe: the service records each episode's fate, marks snapshot views, and a
sender thread drains the words as EpisodeAck messages. Unnamed episodes (incarnation 0) get
no word.
"""

from __future__ import annotations

import threading
from collections import defaultdict

import numpy as np

from common.wire.messages import MAX_ACK_INDICES, EpisodeAck

Source = tuple[int, int]  # (actor_id, incarnation)
WORDS = ("received", "kept", "refused")


class AckBook:
    def __init__(self, durable_on_receipt: bool) -> None:
        self.durable_on_receipt = durable_on_receipt
        self._lock = threading.Lock()
        self._words: dict[Source, dict[str, list[int]]] = {}
        self._unsnapshotted: defaultdict[Source, set[int]] = defaultdict(set)  # taken since the last view
        self._in_view: dict[int, dict[Source, set[int]]] = {}  # views being written, by token
        self._next_token = 0

    def taken(self, actor_id: int, incarnation: int, index: int) -> None:
        if incarnation == 0:
            return
        with self._lock:
            if self.durable_on_receipt:
                self._say((actor_id, incarnation), "kept", index)
            else:
                self._unsnapshotted[(actor_id, incarnation)].add(index)
                self._say((actor_id, incarnation), "received", index)

    def duplicate(self, actor_id: int, incarnation: int, index: int) -> None:
        """Sent again: the actor missed a word. Received while no snapshot holds it yet, else kept."""
        if incarnation == 0:
            return
        source = (actor_id, incarnation)
        with self._lock:
            pending = index in self._unsnapshotted.get(source, ()) or any(
                index in view.get(source, ()) for view in self._in_view.values())
            self._say(source, "received" if pending else "kept", index)

    def refused(self, actor_id: int, incarnation: int, index: int) -> None:
        if incarnation != 0:
            with self._lock:
                self._say((actor_id, incarnation), "refused", index)

    def view_taken(self) -> int:
        """A snapshot's view is taken (under the service's lock): what was taken so far is in it."""
        with self._lock:
            token, self._next_token = self._next_token, self._next_token + 1
            self._in_view[token] = dict(self._unsnapshotted)
            self._unsnapshotted = defaultdict(set)
            return token

    def view_written(self, token: int) -> None:
        with self._lock:
            for source, indices in self._in_view.pop(token, {}).items():
                for index in sorted(indices):
                    self._say(source, "kept", index)

    def view_failed(self, token: int) -> None:
        """Not on disk: its episodes wait for the next snapshot."""
        with self._lock:
            for source, indices in self._in_view.pop(token, {}).items():
                self._unsnapshotted[source].update(indices)

    def drain(self) -> list[EpisodeAck]:
        """The words said since the last drain, one message per source (split past MAX_ACK_INDICES)."""
        with self._lock:
            words, self._words = self._words, {}
        messages = []
        for (actor_id, incarnation), said in words.items():
            longest = max(len(indices) for indices in said.values())
            for start in range(0, longest, MAX_ACK_INDICES):
                arrays = {word: np.asarray(said.get(word, [])[start:start + MAX_ACK_INDICES], dtype=np.int64)
                          for word in WORDS}
                messages.append(EpisodeAck(actor_id=actor_id, incarnation=incarnation, **arrays))
        return messages

    def _say(self, source: Source, word: str, index: int) -> None:
        self._words.setdefault(source, {}).setdefault(word, []).append(index)
