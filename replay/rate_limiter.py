"""The one rate limiter of the system: env steps in, trace batches out, at a fixed ratio.

After Reverb's ``SampleToInsertRatio``, with env steps as inserts and trace
batches (one per learner update) as samples. The replay owns it and is the
only place that counts both:

- *Stage 1*, before updates start: every episode is taken, no batch is served.
  Updates start exactly when the store holds ``start_episodes`` episodes (the
  paper's 999), or, for decreasing epsilon, at ``start_steps`` env steps. The
  env-step count at that moment is the *start mark*.
- *Stage 2*: the updates the system's steps have paid for are
  ``due = (env_steps - start_mark) / env_steps_per_update``; the error is
  ``due - served``. A batch may be served while ``served + 1 <= due + B``
  (the learner at most B updates ahead); actors are told to hold their next
  episode while ``due - served > H`` (the learner more than H behind, H never
  less than B). B, the error buffer, and H, the actors' lead, are fixed numbers
  of updates, not shares of the total. The two differ because an actor that is
  let go delivers nothing until its whole next episode ends: a learner that
  may fall only B behind waits for data while a fast learner's B runs out
  before the episodes come (deploy/bench/pacing_sim.py), while a learner
  that may run far ahead would end a run off the ratio. Steps that arrive
  after the start mark (episodes still in flight when it was reached, the
  random phase's last episodes) are owed like any others.
- Once the run's step budget is reached, actors are held for good, so the
  learner can pay for the last steps and stop on the configured ratio. Episodes
  still in flight then keep arriving and are owed like any others, until the
  learner has been served every update they paid for: then the run is *closed*.
  A closed run takes no more episodes (the replay refuses and counts them), so
  what the learner pays for is final, however long the episodes in flight are.
  An unpaced run (B at least the updates the whole budget pays for) closes at
  the budget.

An episode is inserted whole, so the actors' hold acts at episode boundaries:
the learner can fall behind by H plus the episodes in flight, never more. At
the run's end it pays for all of that before the run closes, so only B, the
learner's lead, bounds the whole run's error.

Pure: no threads, no clock, no I/O. The replay service calls it under its lock
and persists ``state_dict()``, so the counters survive a learner restart (the
replay keeps running) and a replay restart (``replay --resume``). A resumed
replay restores its store from its snapshot (replay/snapshot.py); if that holds
fewer than ``start_episodes`` episodes (none without a snapshot), then, as at the
start, no batch is served until it holds ``start_episodes`` episodes again, and
the steps of that refill move the start mark on (they are not owed, as the random
phase's are not) and are counted in ``refill_env_steps``; meanwhile actors are not
held for the learner.
"""

from __future__ import annotations

import math

from common.pacing import RateLimit, achieved_ratio, is_unpaced, start_mark_of, updates_paid_for
from common.wire.messages import RateState

STATE_VERSION = 1


class RateLimiter:
    """Counts env steps received and batches served; says who must wait."""

    def __init__(self, limit: RateLimit) -> None:
        self.limit = limit
        self.env_steps = 0  # every step received, stored or not
        self.served = 0  # trace batches served since updates started
        self.start_mark: float | None = None  # env steps when updates started (plus refills); None in stage 1
        self.refilling = False  # resumed with an empty store: stage 1 again until start_episodes are stored
        self.refill_env_steps = 0  # steps that refilled a resumed replay's store (not owed)
        self.lost_updates = 0  # batches served that no learner trained on (it died, or their replies never came)
        self.recounted_updates = 0  # updates a learner had made that a resumed replay's counters had lost

    # --- events -------------------------------------------------------------------------

    def on_episode(self, steps: int, episodes_stored: int) -> None:
        """An episode of `steps` steps arrived; the store now holds `episodes_stored` episodes."""
        if steps < 0:
            raise ValueError(f"an episode has >= 0 steps, got {steps}")
        before = self.env_steps
        self.env_steps += steps
        if self.refilling:
            self.start_mark += steps
            self.refill_env_steps += steps
            self.refilling = episodes_stored < self.limit.start_episodes
            return
        if self.start_mark is None:
            self.start_mark = start_mark_of(self.limit, before, self.env_steps, episodes_stored)

    def on_served(self) -> None:
        """One trace batch went out (call only after may_serve() said yes)."""
        self.served += 1

    def on_learner_start(self, updates: int) -> int:
        """A learner process starts from `updates` (its checkpoint's): the batches served beyond them
        were lost with the learner that died, and are owed again. Returns how many."""
        if not 0 <= updates < self.served:
            return 0
        lost, self.served = self.served - updates, updates
        self.lost_updates += lost
        return lost

    def on_learner_updates(self, updates: int, stock: int) -> tuple[int, int]:
        """A running learner has made `updates` and may have at most `stock` batches served for updates it
        has not made (common.pacing.learner_stock). More than served means this replay lost the count of
        batches served since its counters were last saved (it died and resumed); they are counted served
        again, so the learner is not paid twice for the steps that were lost with them. More than `stock`
        below served means replies that never reached it (its session went deaf): they are owed again.
        Returns (recounted, owed again)."""
        if self.start_mark is None or self.refilling:
            return 0, 0
        if updates > self.served:
            gained, self.served = updates - self.served, updates
            self.recounted_updates += gained
            return gained, 0
        lost = self.served - updates - stock
        if lost <= 0:
            return 0, 0
        self.served -= lost
        self.lost_updates += lost
        return 0, lost

    def set_start_by_steps(self, by_steps: bool) -> bool:
        """Changes the start rule (the learner's strategy decides it); False once updates started."""
        if self.start_mark is not None:
            return by_steps == self.limit.start_by_steps
        self.limit = RateLimit(**{**self.limit.__dict__, "start_by_steps": by_steps})
        return True

    # --- decisions ----------------------------------------------------------------------

    @property
    def started(self) -> bool:
        return self.start_mark is not None

    @property
    def updates_due(self) -> float:
        """Updates the steps since the start mark pay for (0 in stage 1)."""
        if self.start_mark is None:
            return 0.0
        return updates_paid_for(self.env_steps, self.start_mark, self.limit.env_steps_per_update)

    @property
    def error(self) -> float:
        """due - served: positive while the learner is behind, negative while it is ahead."""
        return self.updates_due - self.served

    def may_serve(self) -> bool:
        """Whether one more batch keeps the learner within B updates ahead."""
        return self.started and not self.refilling and self.served + 1 <= self.updates_due + self.limit.error_buffer

    @property
    def budget_spent(self) -> bool:
        total = self.limit.total_env_steps
        return total is not None and self.env_steps >= total

    @property
    def unpaced(self) -> bool:
        """B holds nobody: at least the updates the whole budget pays for."""
        return is_unpaced(self.limit.error_buffer, self.limit.total_env_steps, self.limit.env_steps_per_update)

    @property
    def closed(self) -> bool:
        """Budget spent and every update its steps paid for served: no episode is taken any more."""
        return (self.budget_spent and self.started and not self.refilling
                and (self.unpaced or self.served >= self.updates_due))

    def hold_reason(self) -> str:
        """Why actors must hold their next episode: "behind", "budget", or "" (go on)."""
        if self.budget_spent:
            return "budget"
        if self.started and not self.refilling and self.error > self.limit.actors_lead:
            return "behind"
        return ""

    def env_steps_per_update(self) -> float:
        """The achieved ratio since the start mark (nan before the first batch)."""
        return achieved_ratio(self.env_steps, self.start_mark, self.served)

    # --- persistence --------------------------------------------------------------------

    def state_dict(self) -> dict:
        return {"version": STATE_VERSION, "env_steps": self.env_steps, "served": self.served,
                "start_mark": self.start_mark, "refill_env_steps": self.refill_env_steps,
                "lost_updates": self.lost_updates, "recounted_updates": self.recounted_updates}

    def load_state_dict(self, state: dict, episodes_stored: int = 0) -> None:
        """Counters of an earlier replay of the same run whose store now holds episodes_stored
        episodes (restored from its snapshot, or none): if updates had started and fewer than
        start_episodes are stored, they wait for the refill. ValueError if the counters are not sound."""
        try:
            if state["version"] != STATE_VERSION:
                raise ValueError(f"rate limiter state version {state['version']!r}, expected {STATE_VERSION}")
            env_steps, served, mark = state["env_steps"], state["served"], state["start_mark"]
            refill, lost = state.get("refill_env_steps", 0), state.get("lost_updates", 0)
            recounted = state.get("recounted_updates", 0)
        except (KeyError, TypeError, AttributeError) as error:
            raise ValueError(f"malformed rate limiter state ({error!r})") from None
        if not all(_count(value) for value in (env_steps, served, refill, lost, recounted)):
            raise ValueError(f"rate limiter counters must be non-negative integers, got {env_steps!r}, {served!r}")
        if mark is not None and not (isinstance(mark, (int, float)) and 0 <= mark <= env_steps):
            raise ValueError(f"rate limiter start mark {mark!r} must lie in [0, env_steps]")
        if mark is None and served:
            raise ValueError("rate limiter state served batches before updates started")
        self.env_steps, self.served, self.refill_env_steps, self.lost_updates = env_steps, served, refill, lost
        self.recounted_updates = recounted
        self.start_mark = None if mark is None else float(mark)
        self.refilling = mark is not None and episodes_stored < self.limit.start_episodes

    def state(self, now: float) -> RateState:
        """The counters and decisions as the typed message of replay/rate, stamped `now`."""
        achieved = self.env_steps_per_update()
        return RateState(time=now, env_steps=self.env_steps, batches_served=self.served,
                         updates_due=self.updates_due, start_env_steps=self.start_mark,
                         hold_reason=self.hold_reason(), closed=self.closed, refilling=self.refilling,
                         refill_env_steps=self.refill_env_steps, lost_updates=self.lost_updates,
                         recounted_updates=self.recounted_updates, error_buffer_updates=self.limit.error_buffer,
                         hold_updates=self.limit.actors_lead,
                         env_steps_per_update_target=self.limit.env_steps_per_update,
                         env_steps_per_update=achieved if math.isfinite(achieved) else None,
                         unpaced=self.unpaced)


def _count(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def furthest_sound_counters(limit: RateLimit, saved: dict | None, snapshot: dict) -> tuple[dict, str]:
    """Of the counters saved beside the snapshot (rate_limiter.json) and the snapshot's own, the sound ones
    furthest on (env steps, then batches served; the saved file on a tie), and which they are; ValueError
    if neither is sound."""
    options = []
    for state, source in ((saved, "rate_limiter.json"), (snapshot, "the snapshot")):
        try:
            RateLimiter(limit).load_state_dict(state)
        except (ValueError, TypeError, AttributeError):
            continue
        options.append(((state["env_steps"], state["served"]), source == "rate_limiter.json", state, source))
    if not options:
        raise ValueError("neither the snapshot's nor rate_limiter.json's counters are sound")
    _, _, state, source = max(options, key=lambda option: option[:2])
    return state, source
