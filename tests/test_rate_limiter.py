"""The replay's rate limiter (after Reverb's SampleToInsertRatio), case by hand-worked case."""

import math

import pytest

from common.config_values import load_config
from common.pacing import (RateLimit, achieved_ratio, is_unpaced, learner_stock, rate_limit_from_config,
                           start_mark_of)
from common.wire.messages import flat_values
from replay.rate_limiter import RateLimiter


def limiter(per_update=4.0, start_episodes=3, start_steps=100, buffer=2.0, total=None, by_steps=False):
    return RateLimiter(RateLimit(per_update, start_episodes, start_steps, buffer, total, by_steps))


def hundred_due(served: int) -> RateLimiter:
    """Updates started at step 100 (one episode, start_episodes 1); 400 steps later 100 are due; `served` served."""
    rate = limiter(start_episodes=1, buffer=2.0)
    rate.on_episode(100, episodes_stored=1)
    rate.on_episode(400, episodes_stored=2)
    for _ in range(served):
        rate.on_served()
    return rate


def serve_all(rate: RateLimiter) -> int:
    served = 0
    while rate.may_serve():
        rate.on_served()
        served += 1
    return served


def test_stage_one_takes_every_episode_and_serves_nothing():
    rate = limiter()
    rate.on_episode(500, episodes_stored=1)
    rate.on_episode(500, episodes_stored=2)
    assert not rate.started and not rate.may_serve() and rate.hold_reason() == ""
    assert rate.updates_due == 0 and math.isnan(rate.env_steps_per_update())


def test_updates_start_exactly_at_the_configured_episode():
    rate = limiter(start_episodes=3)
    rate.on_episode(10, episodes_stored=1)
    rate.on_episode(20, episodes_stored=2)
    rate.on_episode(30, episodes_stored=3)  # the third stored episode: the mark is 60 steps
    assert rate.started and rate.start_mark == 60
    assert rate.updates_due == 0
    # B = 2 updates of slack ahead: two batches at once, then the learner waits for steps
    assert serve_all(rate) == 2
    rate.on_episode(7, episodes_stored=4)  # 67 - 60 = 7 steps: 1.75 updates due, 2 served
    assert serve_all(rate) == 1  # 3 <= 1.75 + 2
    assert rate.served == 3 and rate.error == pytest.approx(-1.25)


def test_a_short_episode_counts_its_steps_but_not_as_stored():
    rate = limiter(start_episodes=2)
    rate.on_episode(40, episodes_stored=1)
    rate.on_episode(5, episodes_stored=1)  # too short to store: its steps count, the store did not grow
    assert not rate.started and rate.env_steps == 45
    rate.on_episode(15, episodes_stored=2)
    assert rate.start_mark == 60


def test_decreasing_epsilon_starts_at_the_step_count_and_owes_the_rest_of_the_episode():
    rate = limiter(start_steps=100, by_steps=True, buffer=1.0)
    rate.on_episode(90, episodes_stored=1)
    assert not rate.started
    rate.on_episode(30, episodes_stored=2)  # crosses 100 at its 10th step
    assert rate.start_mark == 100
    assert rate.updates_due == pytest.approx(5.0)  # (120 - 100) / 4: the crossing episode's last 20 steps
    assert serve_all(rate) == 6  # 5 due + 1 of slack


def test_actors_hold_while_the_learner_is_more_than_the_buffer_behind():
    rate = limiter(start_episodes=1, buffer=2.0)
    rate.on_episode(20, episodes_stored=1)  # mark 20
    rate.on_episode(8, episodes_stored=2)  # 2 due, 0 served: error 2, not more than B
    assert rate.hold_reason() == ""
    rate.on_episode(4, episodes_stored=3)  # 3 due: error 3 > 2
    assert rate.hold_reason() == "behind"
    rate.on_served()  # error 2: go again
    assert rate.hold_reason() == ""


def test_actors_hold_past_their_own_lead_while_the_learner_keeps_its_own():
    rate = RateLimiter(RateLimit(4.0, 1, 0, error_buffer=2.0, hold_buffer=10.0))
    rate.on_episode(20, episodes_stored=1)  # mark 20
    rate.on_episode(40, episodes_stored=2)  # 10 due, 0 served: error 10, not more than H
    assert rate.hold_reason() == ""
    rate.on_episode(4, episodes_stored=3)  # 11 due: error 11 > 10
    assert rate.hold_reason() == "behind" and rate.state(0.0).hold_updates == 10.0
    assert serve_all(rate) == 13  # the learner's own lead is still B: 11 due + 2


def test_the_actors_lead_is_never_less_than_the_learners():
    unpaced = RateLimiter(RateLimit(4.0, 1, 0, error_buffer=1e9, hold_buffer=10.0))
    unpaced.on_episode(20, episodes_stored=1)
    unpaced.on_episode(4_000, episodes_stored=2)  # 1,000 due, none served
    assert unpaced.hold_reason() == "" and unpaced.limit.actors_lead == 1e9
    with pytest.raises(ValueError, match="hold_buffer"):
        RateLimit(4.0, 1, 0, 2.0, hold_buffer=-1.0)


def test_the_learner_and_the_actors_never_wait_for_each_other_at_once():
    rate = limiter(start_episodes=1, buffer=1.0, per_update=3.0)
    rate.on_episode(1, episodes_stored=1)
    for steps in (1, 2, 3, 5, 8, 13, 21, 2, 1, 40, 3):
        rate.on_episode(steps, episodes_stored=2)
        for _ in range(3):  # any number of serves in between
            assert rate.may_serve() or rate.hold_reason() == ""
            if rate.may_serve():
                rate.on_served()


def test_error_buffer_is_a_number_of_updates_not_a_share():
    rate = limiter(start_episodes=1, buffer=3.0)
    rate.on_episode(0, episodes_stored=1)
    rate.on_episode(400_000, episodes_stored=2)  # 100,000 due
    assert serve_all(rate) == 100_003  # three ahead, whatever the total
    rate.on_episode(4 * 4, episodes_stored=3)  # 100,004 due: error 1
    assert rate.hold_reason() == ""
    rate.on_episode(4 * 3, episodes_stored=4)  # 100,007 due: error 4 > 3
    assert rate.hold_reason() == "behind"


def test_achieved_ratio_counts_from_the_start_mark():
    rate = limiter(start_episodes=1, per_update=4.0, buffer=1.0)
    rate.on_episode(1_000, episodes_stored=1)  # random phase, before the mark: not owed
    for _ in range(10):
        rate.on_episode(40, episodes_stored=2)
        serve_all(rate)
    # 400 steps after the mark; the learner may be one update ahead: 101 served
    assert rate.served == 101 and rate.env_steps_per_update() == pytest.approx(400 / 101)


def test_budget_holds_the_actors_for_good():
    rate = limiter(start_episodes=1, total=100, buffer=1.0)
    rate.on_episode(60, episodes_stored=1)
    assert rate.hold_reason() == ""
    rate.on_episode(60, episodes_stored=2)  # 120 >= 100
    assert rate.hold_reason() == "budget"
    serve_all(rate)
    assert rate.hold_reason() == "budget" and rate.served == 16  # (120 - 60) / 4 + 1


def test_the_run_closes_once_the_budget_is_spent_and_every_update_it_pays_for_is_served():
    rate = limiter(start_episodes=1, total=100, buffer=2.0)
    rate.on_episode(60, episodes_stored=1)  # the mark: 60
    for _ in range(8):
        rate.on_served()  # 8 updates: 32 steps paid for
    rate.on_episode(50, episodes_stored=2)  # 110 >= 100: budget spent, (110 - 60) / 4 = 12.5 due
    assert rate.budget_spent and not rate.closed and not rate.state(0.0).closed
    rate.on_episode(30, episodes_stored=3)  # in flight at the budget: owed too, 20 due
    for _ in range(12):
        rate.on_served()
    assert rate.served == 20 and rate.closed and rate.state(0.0).closed


def test_an_unpaced_run_closes_at_its_budget():
    rate = limiter(start_episodes=1, total=100, buffer=1e9)
    rate.on_episode(60, episodes_stored=1)
    assert rate.unpaced and not rate.closed
    rate.on_episode(60, episodes_stored=2)
    assert rate.served == 0 and rate.closed


def test_a_run_reopens_when_a_restarted_learner_owes_lost_updates_again():
    rate = limiter(start_episodes=1, total=100, buffer=2.0)
    rate.on_episode(100, episodes_stored=1)
    rate.on_episode(40, episodes_stored=2)  # 10 due
    assert serve_all(rate) == 12 and rate.closed  # 10 due, B = 2 ahead
    assert rate.on_learner_start(7) == 5 and not rate.closed  # its checkpoint kept 7: 3 of the 10 owed again
    serve_all(rate)
    assert rate.closed


def test_the_start_rule_follows_the_learner_until_updates_start():
    rate = limiter(start_episodes=2, start_steps=50)
    assert rate.set_start_by_steps(True)
    rate.on_episode(60, episodes_stored=1)
    assert rate.start_mark == 50
    assert not rate.set_start_by_steps(False)  # too late: updates started by steps
    assert rate.set_start_by_steps(True)


def test_state_round_trips_and_bad_state_is_refused():
    rate = limiter(start_episodes=1)
    rate.on_episode(30, episodes_stored=1)
    rate.on_episode(12, episodes_stored=2)
    serve_all(rate)
    again = limiter(start_episodes=1)
    again.load_state_dict(rate.state_dict())
    assert again.state_dict() == rate.state_dict() and again.refilling
    good = rate.state_dict()
    for bad in ({**good, "version": 9}, {**good, "served": -1}, {**good, "env_steps": 1.5},
                {**good, "start_mark": 10_000}, {**good, "start_mark": None}, {**good, "refill_env_steps": -3},
                {"env_steps": 3}, None):
        with pytest.raises(ValueError):
            limiter().load_state_dict(bad)


def test_state_carries_every_counter_and_an_older_state_without_the_newer_ones_loads_as_zero():
    # Found by mutation testing: the round trip above has no refill, no lost and no recounted update,
    # so a key misspelt on one side (or a default other than 0) went unseen
    rate = limiter(start_episodes=2, buffer=2.0)
    rate.load_state_dict({"version": 1, "env_steps": 1_000, "served": 200, "start_mark": 200.0}, episodes_stored=1)
    assert (rate.refill_env_steps, rate.lost_updates, rate.recounted_updates) == (0, 0, 0)
    rate.on_episode(20, episodes_stored=2)  # the refill: 20 steps
    assert rate.on_learner_start(197) == 3  # 3 lost
    assert rate.on_learner_updates(199, stock=7) == (2, 0)  # 2 recounted
    assert rate.state_dict() == {"version": 1, "env_steps": 1_020, "served": 199, "start_mark": 220.0,
                                 "refill_env_steps": 20, "lost_updates": 3, "recounted_updates": 2}
    again = limiter(start_episodes=2, buffer=2.0)
    again.load_state_dict(rate.state_dict(), episodes_stored=2)
    assert (again.refill_env_steps, again.lost_updates, again.recounted_updates) == (20, 3, 2)
    with pytest.raises(ValueError, match="rate limiter state version 9, expected 1"):
        again.load_state_dict({**rate.state_dict(), "version": 9})
    with pytest.raises(ValueError, match="malformed rate limiter state"):
        again.load_state_dict({"version": 1})


def test_a_loaded_state_is_taken_at_its_bounds_and_refused_past_them_by_name():
    # Found by mutation testing: each bound of the loaded counters from both sides
    rate = limiter(start_episodes=2)
    rate.load_state_dict({"version": 1, "env_steps": 40, "served": 0, "start_mark": None}, episodes_stored=1)
    assert not rate.started and rate.env_steps == 40  # stage 1, saved before updates started
    rate.load_state_dict({"version": 1, "env_steps": 40, "served": 0, "start_mark": 0}, episodes_stored=2)
    assert rate.start_mark == 0.0 and not rate.refilling  # updates started at step 0; the store is full again
    rate.load_state_dict({"version": 1, "env_steps": 40, "served": 3, "start_mark": 40.0}, episodes_stored=2)
    assert rate.start_mark == 40.0  # started by the last episode saved
    good = {"version": 1, "env_steps": 40, "served": 3, "start_mark": 20.0}
    for bad, message in (({"served": -1}, r"counters must be non-negative integers, got 40, -1"),
                         ({"start_mark": 41.0}, r"start mark 41.0 must lie in \[0, env_steps\]"),
                         ({"start_mark": -1.0}, r"start mark -1.0 must lie in \[0, env_steps\]"),
                         ({"start_mark": None}, "^rate limiter state served batches before updates started$")):
        with pytest.raises(ValueError, match=message):
            rate.load_state_dict({**good, **bad}, episodes_stored=2)


def test_lost_and_recounted_updates_add_up_over_several_restarts():
    rate = hundred_due(served=10)
    assert rate.on_learner_start(10) == 0  # its checkpoint has every update served: nothing lost
    assert rate.on_learner_start(12) == 0  # ahead of the count: nothing to owe again (the next test's case)
    assert rate.on_learner_start(0) == 10  # a learner with no checkpoint lost every update served
    for _ in range(6):
        rate.on_served()
    assert rate.on_learner_start(4) == 2 and rate.lost_updates == 12  # the second death adds to the first
    assert rate.on_learner_updates(7, stock=7) == (3, 0) and rate.on_learner_updates(9, stock=7) == (2, 0)
    assert rate.recounted_updates == 5 and rate.served == 9


def test_batches_served_beyond_what_a_running_learner_can_hold_are_owed_again():
    # A learner whose session went deaf: its requests reached the replay, the replies never came back
    rate = hundred_due(served=60)
    assert rate.on_learner_updates(53, stock=7) == (0, 0) and rate.served == 60  # 7 in its hands or in transit
    assert rate.on_learner_updates(40, stock=7) == (0, 13) and rate.served == 47  # 13 replies never came
    assert rate.lost_updates == 13 and rate.error == 100 - 47
    assert rate.on_learner_updates(40, stock=7) == (0, 0)  # owed once, not again
    again = limiter(start_episodes=1, buffer=2.0)
    again.load_state_dict(rate.state_dict(), episodes_stored=2)
    assert again.lost_updates == 13 and again.served == 47
    refilling = limiter(start_episodes=2, buffer=2.0)
    refilling.load_state_dict(rate.state_dict(), episodes_stored=1)
    assert refilling.on_learner_updates(0, stock=7) == (0, 0)  # refilling: no batch is served, none owed


def test_the_replays_stats_name_every_counter_and_decision():
    # The replay's rate message (and the rate inside its stats), flattened as logs keep it; each checked by hand
    waiting = limiter(start_episodes=2, per_update=4.0, buffer=2.0)
    waiting.on_episode(30, episodes_stored=1)
    assert flat_values(waiting.state(5.0)) == {  # no start mark, no ratio yet
        "time": 5.0, "env_steps": 30, "batches_served": 0, "updates_due": 0.0,
        "hold_reason": "", "closed": 0, "refilling": 0, "refill_env_steps": 0, "lost_updates": 0,
        "recounted_updates": 0, "error_buffer_updates": 2.0, "hold_updates": 2.0, "env_steps_per_update_target": 4.0,
        "unpaced": 0}
    behind = limiter(start_episodes=1, per_update=4.0, buffer=2.0)
    behind.on_episode(100, episodes_stored=1)
    behind.on_episode(40, episodes_stored=2)  # 10 due
    for _ in range(6):
        behind.on_served()  # 4 behind, more than B = 2
    assert behind.on_learner_start(5) == 1
    assert flat_values(behind.state(5.0)) == {
        "time": 5.0, "env_steps": 140, "batches_served": 5, "updates_due": 10.0, "start_env_steps": 100.0,
        "hold_reason": "behind", "closed": 0, "refilling": 0, "refill_env_steps": 0, "lost_updates": 1,
        "recounted_updates": 0, "error_buffer_updates": 2.0, "hold_updates": 2.0, "env_steps_per_update_target": 4.0,
        "env_steps_per_update": 8.0, "unpaced": 0}
    resumed = limiter(start_episodes=2, per_update=4.0, buffer=1.0, total=1_000)
    resumed.load_state_dict({"version": 1, "env_steps": 1_000, "served": 200, "start_mark": 200.0,
                             "refill_env_steps": 5, "lost_updates": 2, "recounted_updates": 4}, episodes_stored=1)
    assert flat_values(resumed.state(5.0)) == {
        "time": 5.0, "env_steps": 1_000, "batches_served": 200, "updates_due": 200.0, "start_env_steps": 200.0,
        "hold_reason": "budget", "closed": 0, "refilling": 1, "refill_env_steps": 5,
        "lost_updates": 2, "recounted_updates": 4, "error_buffer_updates": 1.0, "hold_updates": 1.0, "env_steps_per_update_target": 4.0,
        "env_steps_per_update": 4.0, "unpaced": 0}
    closed = limiter(start_episodes=1, per_update=4.0, buffer=2.0, total=100)
    closed.on_episode(100, episodes_stored=1)
    closed.on_episode(40, episodes_stored=2)
    assert serve_all(closed) == 12
    assert closed.state(0.0).closed and closed.state(0.0).env_steps_per_update == 40 / 12
    free = limiter(start_episodes=1, per_update=4.0, buffer=1e9, total=100)
    assert free.state(0.0).unpaced and not closed.state(0.0).unpaced


def test_a_resumed_replay_refills_its_store_before_serving_and_does_not_owe_the_refill():
    rate = limiter(start_episodes=2, buffer=1.0)
    rate.load_state_dict({"version": 1, "env_steps": 1_000, "served": 200, "start_mark": 200.0})
    assert rate.refilling and not rate.may_serve()
    assert rate.hold_reason() == ""  # 200 due, 200 served; and never "behind" while refilling
    rate.on_episode(30, episodes_stored=1)
    assert rate.refilling and not rate.may_serve() and rate.hold_reason() == ""
    rate.on_episode(50, episodes_stored=2)  # refilled: the mark moved by the refill's 80 steps
    assert not rate.refilling and rate.start_mark == 280 and rate.refill_env_steps == 80
    assert rate.updates_due == 200 and serve_all(rate) == 1  # one ahead, as before the restart
    rate.on_episode(40, episodes_stored=3)
    assert rate.updates_due == 210 and serve_all(rate) == 10
    assert rate.env_steps_per_update() == pytest.approx((1_120 - 280) / 211)


def test_settings_come_from_the_config():
    config = load_config("paper")
    limit = rate_limit_from_config(config)
    assert (limit.env_steps_per_update, limit.start_episodes, limit.start_steps, limit.total_env_steps) == \
        (4.0, 999, 50_000, 1_000_000)
    assert limit.error_buffer == config.pace.error_buffer_updates and not limit.start_by_steps
    assert limit.hold_buffer == config.pace.hold_updates
    assert rate_limit_from_config(config, strategy="decreasing").start_by_steps
    same_start = load_config("paper", overrides={"pace.start_by": "steps"})
    assert rate_limit_from_config(same_start, strategy="bmc").start_by_steps
    by_episodes = load_config("paper", overrides={"pace.start_by": "episodes"})
    assert not rate_limit_from_config(by_episodes, strategy="decreasing").start_by_steps
    with pytest.raises(ValueError, match="error_buffer"):
        RateLimit(4.0, 1, 0, 0.5)


def test_the_settings_are_refused_below_their_bounds_and_taken_at_them():
    # Found by mutation testing (deploy/bench/mutation.py): each bound checked on both sides, and the
    # message names the setting, so that a user who sets it wrong reads which one
    RateLimit(0.5, 1, 0, 1.0)  # fewer env steps than updates is a valid ratio: only > 0 is required
    with pytest.raises(ValueError, match="env_steps_per_update must be > 0, got 0"):
        RateLimit(0.0, 1, 0, 1.0)
    with pytest.raises(ValueError, match="start_episodes must be >= 1 and start_steps >= 0, got 0 and 5"):
        RateLimit(4.0, 0, 5, 1.0)  # the episodes wrong, the steps right: still refused
    with pytest.raises(ValueError, match="got 1 and -1"):
        RateLimit(4.0, 1, -1, 1.0)
    with pytest.raises(ValueError, match="an episode has >= 0 steps, got -1"):
        limiter().on_episode(-1, episodes_stored=0)


def test_the_start_mark_at_the_exact_start_episode_and_the_exact_start_step():
    by_episodes = RateLimit(4.0, start_episodes=3, start_steps=100, error_buffer=1.0)
    assert start_mark_of(by_episodes, 50, 80, episodes_stored=2) is None
    assert start_mark_of(by_episodes, 50, 80, episodes_stored=3) == 80.0  # the third episode: the steps so far
    by_steps = RateLimit(4.0, start_episodes=3, start_steps=100, error_buffer=1.0, start_by_steps=True)
    assert start_mark_of(by_steps, 90, 99, episodes_stored=1) is None
    assert start_mark_of(by_steps, 90, 100, episodes_stored=1) == 100.0  # reaching start_steps exactly starts


def test_the_achieved_ratio_is_nan_before_the_start_or_the_first_update_and_exact_after():
    assert math.isnan(achieved_ratio(500.0, None, 5))  # updates made, but no mark (a restored count)
    assert math.isnan(achieved_ratio(500.0, 100.0, 0))  # a mark, no update yet: not a division by zero
    assert achieved_ratio(500.0, 100.0, 1) == 400.0  # from the first update on
    assert achieved_ratio(500.0, 100.0, 8) == 50.0


def test_unpaced_exactly_when_the_buffer_covers_the_whole_budget():
    # 1,000 env steps at 4 per update pay for 250 updates: a buffer of 250 holds nobody, 249 may
    assert is_unpaced(250.0, 1_000, 4.0) and not is_unpaced(249.0, 1_000, 4.0)
    assert not is_unpaced(1e9, None, 4.0)  # no budget: always paced


def test_a_resumed_replay_counts_the_updates_a_running_learner_made_beyond_its_saved_counters():
    rate = hundred_due(served=20)
    saved = rate.state_dict()
    for _ in range(30):
        rate.on_served()  # served, then the replay dies before saving again
    resumed = limiter(start_episodes=1, buffer=2.0)
    resumed.load_state_dict(saved, episodes_stored=2)
    assert resumed.served == 20
    assert resumed.on_learner_updates(50, stock=7) == (30, 0) and resumed.served == 50  # the learner made 50
    assert resumed.on_learner_updates(48, stock=7) == (0, 0) and resumed.served == 50  # sent before two came back
    again = limiter(start_episodes=1, buffer=2.0)
    again.load_state_dict(resumed.state_dict(), episodes_stored=2)
    assert (again.recounted_updates, again.state(0.0).recounted_updates) == (30, 30)
    assert limiter().on_learner_updates(5, stock=7) == (0, 0)  # before updates start there is nothing to count
