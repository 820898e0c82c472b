"""Episodes an actor began while told to hold, refused: the rate limiter's bound kept against an actor
that does not hear replay/rate, or does not obey it.

The limiter bounds the learner's lag by the actors' lead plus the episodes in flight
(replay/rate_limiter.py) because no actor begins an episode while told to hold. An actor holds on the
word, or by itself after actor.silence_hold_s without any word (actor/mailbox.py). So once the actors
have been told to hold for longer than that plus two stats periods (the grace), an actor can deliver
only episodes it had in hand: its envs_per_actor running ones and queue_episodes queued ones past the
highest index it had delivered, and some on the wire. The allowance is twice that, from what the episode
states (an actor started with more simulators than the run's config says) or the run's config, whichever
is more; an episode past it is refused, counted, and refused again when sent again.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from typing import Callable

MAX_REMEMBERED = 100_000  # refused episodes remembered, so that one sent again is refused again
MAX_IN_HAND = 4_096  # more than any actor holds: a statement beyond counts as this


class HoldGuard:
    def __init__(self, grace_s: float, allowance: int, clock: Callable[[], float] = time.monotonic) -> None:
        self.grace_s, self.allowance = grace_s, allowance
        self._clock = clock
        self._held_since: float | None = None
        self._marks: dict[tuple[int, int], int] = {}  # per actor incarnation: its highest index at the grace's end
        self._refused: OrderedDict[tuple[int, int, int], None] = OrderedDict()
        self.refused = 0  # refusals, resends included

    @classmethod
    def of(cls, config) -> "HoldGuard":
        return cls(config.actor.silence_hold_s + 2 * config.replay.stats_period_s,
                   2 * (config.actor.envs_per_actor + config.actor.queue_episodes))

    def note_hold(self, holding: bool) -> None:
        """The limiter's word now: whether the actors are told to hold."""
        if not holding:
            self._held_since = None
            self._marks.clear()
        elif self._held_since is None:
            self._held_since = self._clock()

    def admits(self, actor_id: int, incarnation: int, index: int, highest: int, in_hand: int = 0) -> bool:
        """Whether the episode may be taken; `highest` is the highest index of its incarnation taken so far,
        `in_hand` what the episode says its actor can have in hand (0: not stated)."""
        name = (actor_id, incarnation, index)
        if name not in self._refused:
            if incarnation == 0 or self._held_since is None or self._clock() - self._held_since < self.grace_s:
                return True
            allowance = max(self.allowance, 2 * min(in_hand, MAX_IN_HAND))
            if index <= self._marks.setdefault((actor_id, incarnation), highest) + allowance:
                return True
            self._refused[name] = None
            while len(self._refused) > MAX_REMEMBERED:
                self._refused.popitem(last=False)
        self.refused += 1
        return False
