"""The pace of a fast learner (deploy/bench/pacing_sim.py): the real rate limiter, the actors' mailboxes and
gates and the learner's run clock on a simulated clock, in short runs of 12 actors.

Actors 20% faster than the ratio needs: the actors' lead of the defaults keeps the learner busy, where a lead of
B alone (before issue 40) left it waiting a sixth of the time; the run closes paid for either way."""

import dataclasses

import pytest

from common.config import PaceConfig
from deploy.bench.pacing_sim import Scenario, row, simulate

DEFAULTS = PaceConfig()
SHORT = Scenario(updates_per_s=300.0, error_buffer=DEFAULTS.error_buffer_updates, hold_buffer=DEFAULTS.hold_updates,
                 free_over_need=1.2, episodes="mixed", start_steps=8_000, budget_updates=12_000)


@pytest.fixture(scope="module")
def before_and_after():
    return simulate(dataclasses.replace(SHORT, hold_buffer=None)), simulate(SHORT)


def test_the_actors_lead_keeps_a_fast_learner_busy(before_and_after):
    before, after = before_and_after
    assert before.idle_share > 0.15
    assert after.idle_share < 0.10


def test_the_run_closes_exactly_paid_for_whatever_the_actors_lead(before_and_after):
    for outcome in before_and_after:
        assert outcome.updates >= SHORT.budget_updates
        assert -1.0 < outcome.end_shortfall <= 0.0  # the learner behind at the budget pays the rest, not more
        assert abs(outcome.deviation(outcome.end_ratio)) < 0.01


def test_actors_too_slow_end_within_the_learners_lead():
    outcome = simulate(dataclasses.replace(SHORT, free_over_need=0.8, budget_updates=4_000))
    assert outcome.idle_share > 0.15  # no pace makes up for missing steps
    assert -SHORT.error_buffer <= outcome.end_shortfall <= 0.0
    assert abs(outcome.deviation(outcome.end_ratio)) < 0.01


def test_the_simulation_is_deterministic_and_tabulates(before_and_after):
    again = simulate(SHORT)
    assert dataclasses.astuple(again) == dataclasses.astuple(before_and_after[1])
    line = row([again])
    assert line.startswith("| 300 | 1.2 | mixed | 50 | 1500 |") and line.count("|") == 11
