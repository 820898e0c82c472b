"""Which episodes the replay has taken: none twice, and the ones that never arrived counted.

An actor process names each episode by (actor_id, incarnation, episode_index): the
incarnation is a random number drawn when the process starts and the index counts
its episodes from 0. The ledger remembers, per (actor_id, incarnation), the highest
index taken and the indices below it that have not arrived (gaps), so:

- an index taken before is a duplicate (a log played into the run again, a resent
  message) and is refused;
- a gap is an episode that never reached this replay (lost with a replay that died
  before its snapshot, in transit, or dropped by its actor); ``missing`` counts them,
  and an episode that fills a gap late is taken.

Bounded: at most MAX_SOURCES incarnations are remembered (the least recently heard
is forgotten first) and at most MAX_GAPS open gaps per incarnation (older ones are
forgotten, still counted). Episodes without a name (incarnation 0, older senders) are
always taken. Pure: the replay calls it under its lock and snapshots ``state_dict()``.
"""

from __future__ import annotations

from collections import OrderedDict

MAX_SOURCES = 4096
MAX_GAPS = 1024
STATE_VERSION = 1


class EpisodeLedger:
    def __init__(self) -> None:
        self._sources: OrderedDict[tuple[int, int], tuple[int, set[int]]] = OrderedDict()
        self.missing = 0  # indices skipped over that have not arrived since
        self.duplicates = 0

    def admit(self, actor_id: int, incarnation: int, index: int) -> bool:
        """Records the episode; False if it was taken before (a duplicate)."""
        if incarnation == 0:
            return True
        source = (actor_id, incarnation)
        highest, gaps = self._sources.pop(source, (-1, set()))
        if index <= highest:
            if index not in gaps:
                self._sources[source] = (highest, gaps)
                self.duplicates += 1
                return False
            gaps.discard(index)
            self.missing -= 1
        else:
            skipped = index - highest - 1
            self.missing += skipped
            gaps.update(range(max(highest + 1, index - MAX_GAPS), index))
            highest = index
            if len(gaps) > MAX_GAPS:
                gaps = set(sorted(gaps)[-MAX_GAPS:])
        self._sources[source] = (highest, gaps)
        while len(self._sources) > MAX_SOURCES:
            self._sources.popitem(last=False)
        return True

    def highest(self, actor_id: int, incarnation: int) -> int:
        """The highest index taken of an incarnation (-1: none)."""
        return self._sources.get((actor_id, incarnation), (-1, set()))[0]

    @property
    def sources(self) -> int:
        return len(self._sources)

    def state_dict(self) -> dict:
        return {"version": STATE_VERSION, "missing": self.missing, "duplicates": self.duplicates,
                "sources": [[actor, incarnation, highest, sorted(gaps)]
                            for (actor, incarnation), (highest, gaps) in self._sources.items()]}

    def load_state_dict(self, state: dict) -> None:
        """ValueError if the state is not a ledger's."""
        try:
            if state["version"] != STATE_VERSION:
                raise ValueError(f"ledger state version {state['version']!r}, expected {STATE_VERSION}")
            sources = OrderedDict(((int(actor), int(incarnation)), (int(highest), {int(gap) for gap in gaps}))
                                  for actor, incarnation, highest, gaps in state["sources"])
            missing, duplicates = int(state["missing"]), int(state["duplicates"])
        except (KeyError, TypeError, ValueError) as error:
            raise ValueError(f"malformed ledger state ({error!r})") from None
        self._sources, self.missing, self.duplicates = sources, missing, duplicates
