"""The run's end with long episodes in flight: every episode the replay stored is paid for, and the run's
ratio stays within pace.error_buffer_updates, however long the episodes.

The real RateLimiter (the replay's) and RunClock (the learner's) on a simulated clock: several actors drive
episodes of up to env.max_steps steps, obey the replay's hold at episode boundaries, and deliver each episode
when it ends; the learner takes a batch whenever the limiter serves one and hears the replay's numbers one
tick late, as it would over the wire. Once the budget is spent, the episodes still in flight keep arriving:
the replay takes them until the run closes and refuses (and counts) the rest.
"""

from dataclasses import dataclass, field

import numpy as np
import pytest

from common.pacing import RateLimit
from learner.service import RunClock
from replay.rate_limiter import RateLimiter

TICK_S = 0.05
MAX_STEPS = 2_000  # env.max_steps: the cap of the paper's episodes


@dataclass
class Ended:
    """What the simulation saw."""
    limiter: RateLimiter
    updates: int
    in_flight_at_budget: list[int] = field(default_factory=list)  # steps left of each, when the budget was spent
    taken_after_budget: int = 0  # episodes the replay took after the budget was spent (in flight then)
    refused: int = 0  # episodes that arrived after the run closed

    @property
    def shortfall(self) -> float:
        """Updates the stored steps paid for and the learner did not make (> 0: unpaid steps)."""
        return self.limiter.updates_due - self.updates

    @property
    def ratio(self) -> float:
        return (self.limiter.env_steps - self.limiter.start_mark) / self.updates


def simulate(seed: int, actors: int = 4, per_update: float = 4.0, buffer: float = 2.0, budget: int = 60_000,
             actor_steps_per_s: float = 100.0, updates_per_s: float = 100.0) -> Ended:
    rng = np.random.default_rng(seed)
    limiter = RateLimiter(RateLimit(per_update, start_episodes=20, start_steps=0, error_buffer=buffer,
                                    total_env_steps=budget))
    clock = RunClock()
    left = [0.0] * actors  # steps left of each actor's episode; 0: idle, waiting for the replay's word
    length = [0] * actors
    ended = Ended(limiter, updates=0)
    stored, credit, learning = 0, 0.0, True
    heard = None  # the limiter's state as the learner last heard it
    while learning or any(left):
        for actor in range(actors):
            if left[actor] > 0:
                left[actor] = max(0.0, left[actor] - actor_steps_per_s * TICK_S)
                if left[actor] == 0:
                    if limiter.closed:
                        ended.refused += 1
                        continue
                    stored += 1
                    ended.taken_after_budget += limiter.budget_spent
                    limiter.on_episode(length[actor], stored)
                    if limiter.budget_spent and not ended.in_flight_at_budget:
                        ended.in_flight_at_budget = [int(steps) for steps in left if steps > 0]
            elif not limiter.hold_reason():
                length[actor] = int(rng.integers(10, MAX_STEPS + 1))
                left[actor] = float(length[actor])
        if learning:
            if heard is not None:
                clock.observe_rate(heard)
            if clock.finished(ended.updates):
                learning = False
                continue
            credit += updates_per_s * TICK_S
            while credit >= 1 and limiter.may_serve():
                limiter.on_served()
                ended.updates += 1
                credit -= 1
            credit = min(credit, 1.0)
            heard = limiter.state(0.0)
    return ended


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_stored_episode_is_paid_for_with_long_episodes_in_flight(seed):
    ended = simulate(seed)
    # the case it is about: steps in flight at the budget worth far more than B (2) updates
    assert len(ended.in_flight_at_budget) >= 2 and sum(ended.in_flight_at_budget) > 500
    assert ended.limiter.closed
    assert -2.0 <= ended.shortfall <= 0.0  # paid for every stored step, at most B updates ahead
    assert abs(ended.ratio - 4.0) * ended.updates <= 2.0 * 4.0  # within B updates' worth of steps


@pytest.mark.parametrize("updates_per_s", [60.0, 120.0, 400.0])
def test_the_learners_speed_changes_who_waits_not_the_ratio(updates_per_s):
    ended = simulate(seed=5, updates_per_s=updates_per_s)
    assert ended.limiter.closed and -2.0 <= ended.shortfall <= 0.0


def test_episodes_in_flight_are_taken_until_the_run_closes_and_refused_after():
    seen = [simulate(seed) for seed in range(4)]
    assert sum(ended.taken_after_budget for ended in seen) >= 1 and sum(ended.refused for ended in seen) >= 1


def test_an_unpaced_run_stops_once_closed_at_its_budget():
    ended = simulate(seed=4, buffer=1e9)
    assert ended.limiter.closed and ended.taken_after_budget == 0  # closed by the crossing episode
    assert ended.updates < ended.limiter.updates_due  # the unpaced learner does not pay the rest
