"""The replay's rate limiter (after Reverb's SampleToInsertRatio), case by hand-worked case."""

import math

import pytest

from common.config_values import load_config
from common.pacing import RateLimit, rate_limit_from_config
from replay.rate_limiter import RateLimiter


def limiter(per_update=4.0, start_episodes=3, start_steps=100, buffer=2.0, total=None, by_steps=False):
    return RateLimiter(RateLimit(per_update, start_episodes, start_steps, buffer, total, by_steps))


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
    assert rate.hold_reason() == "behind" and rate.values()["hold_updates"] == 10.0
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
    assert rate.budget_spent and not rate.closed and rate.values()["closed"] == 0
    rate.on_episode(30, episodes_stored=3)  # in flight at the budget: owed too, 20 due
    for _ in range(12):
        rate.on_served()
    assert rate.served == 20 and rate.closed and rate.values()["closed"] == 1


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
    assert limit.error_buffer == config.replay.error_buffer_updates and not limit.start_by_steps
    assert limit.hold_buffer == config.replay.hold_updates
    assert rate_limit_from_config(config, strategy="decreasing").start_by_steps
    same_start = load_config("paper", overrides={"learner.start_by": "steps"})
    assert rate_limit_from_config(same_start, strategy="bmc").start_by_steps
    by_episodes = load_config("paper", overrides={"learner.start_by": "episodes"})
    assert not rate_limit_from_config(by_episodes, strategy="decreasing").start_by_steps
    with pytest.raises(ValueError, match="error_buffer"):
        RateLimit(4.0, 1, 0, 0.5)


def test_a_resumed_replay_counts_the_updates_a_running_learner_made_beyond_its_saved_counters():
    rate = limiter(start_episodes=1, buffer=2.0)
    rate.on_episode(100, episodes_stored=1)
    rate.on_episode(400, episodes_stored=2)  # 100 due
    for _ in range(20):
        rate.on_served()
    saved = rate.state_dict()
    for _ in range(30):
        rate.on_served()  # served, then the replay dies before saving again
    resumed = limiter(start_episodes=1, buffer=2.0)
    resumed.load_state_dict(saved, episodes_stored=2)
    assert resumed.served == 20
    assert resumed.on_learner_updates(50) == 30 and resumed.served == 50  # the learner made 50
    assert resumed.on_learner_updates(48) == 0 and resumed.served == 50  # a request sent before two came back
    again = limiter(start_episodes=1, buffer=2.0)
    again.load_state_dict(resumed.state_dict(), episodes_stored=2)
    assert (again.recounted_updates, again.values()["recounted_updates"]) == (30, 30)
    assert limiter().on_learner_updates(5) == 0  # before updates start there is nothing to count
