"""When an idle simulator may begin its next episode (EpisodeGate, from the replay's word in the
mailbox), and the holds logged once per period (HoldLog).
"""

from __future__ import annotations

import logging
import time
from typing import Callable

from actor.mailbox import Mailbox
from common.logs import Every

HOLD_WHY = {"budget": "the run's step budget is spent",
            "policy": "updates have started and the learner's weights and exploration state have not come",
            "replay": "no replay is alive to count the steps (a restart): waiting for its word",
            "silent": "no word from the replay on replay/rate: this actor may no longer hear the hub (its session "
                      "reopens after actor.silence_reopen_s)"}
HOLD_LOG_S = 10.0  # a paced run holds nearly every episode briefly: one line per period counts them

log = logging.getLogger("actor")


class EpisodeGate:
    """Whether an idle simulator may begin its next episode: while `more` says the actor wants more
    episodes and the replay's rate limiter does not say hold. Logs the holds.

    A held simulator waits while the actor's others go on with their episodes. The limiter counts an
    episode's steps when it arrives and bounds the learner's lag by its buffer plus the episodes in
    flight; a running episode is in flight whether its simulator pauses or not, as on envs_per_actor
    separate actors, so pausing it would only delay steps that are owed anyway. What keeps the ratio
    exact is that no simulator begins an episode while the replay says hold.

    Once updates have started, an actor without the learner's policy (`has_policy` False) holds as well.

    A hold, for the log, lasts from the first refused start until the replay lets the next one go: the
    replay's word holds all of the actor's idle simulators at once."""

    def __init__(self, mailbox: Mailbox, holds: HoldLog, more: Callable[[], bool],
                 has_policy: Callable[[], bool] = lambda: True) -> None:
        self.mailbox = mailbox
        self.holds = holds
        self.more = more
        self.has_policy = has_policy
        self.held = False

    def __call__(self) -> bool:
        if not self.more():
            return False
        reason = self.mailbox.must_hold(self.has_policy())
        if reason:
            if not self.held:
                self.holds.begin()
                self.held = True
            self.holds.tick(reason)
            return False
        if self.held:
            self.holds.end()
            self.held = False
        return True


class HoldLog:
    """The rate limiter's holds, logged once per period with their count and time, not once per hold."""

    def __init__(self, period_s: float, clock=time.monotonic) -> None:
        self._every = Every(period_s, clock)
        self._clock = clock
        self._line_at = clock()
        self._held = 0  # holds begun since the last line (an ongoing one counts again in the next)
        self._held_s = 0.0  # time held since the last line, but for the ongoing hold
        self._since: float | None = None  # start of the ongoing hold, or of its part since the last line

    def begin(self) -> None:
        self._held += 1
        self._since = self._clock()

    def end(self) -> None:
        self._held_s += self._clock() - self._since
        self._since = None

    def tick(self, reason: str) -> None:
        if not self._every.due():
            return
        now = self._clock()
        ongoing = self._since is not None
        held_s = self._held_s + (now - self._since if ongoing else 0.0)
        why = HOLD_WHY.get(reason, "the learner is behind")
        log.info("held %d episode(s) for %.0fs of the last %.0fs: %s", self._held, held_s, now - self._line_at, why)
        self._line_at, self._held, self._held_s = now, int(ongoing), 0.0
        if ongoing:
            self._since = now
