"""What the learner counts: BMC observations per env step, the achieved ratio, when the run is paid for."""

import math
import threading

import numpy as np
import pytest

from common.config_values import load_config
from common.wire.frames import FrameStack
from common.wire.messages import RateState, Stats, TraceBatch
from learner.process import _first_batch
from learner.service import LearnerService, RunClock
from wire_examples import example_rate, example_replay_stats

SIZE, STEPS, TRACES, MASK = 36, 4, 3, 2  # 3 traces x 2 unmasked steps: 6 transitions per batch


def config_with(tmp_path, **overrides):
    return load_config("smoke", overrides={
        "network.frame_height": SIZE, "network.frame_width": SIZE, "network.lstm_units": 16,
        "learner.trace_length": STEPS, "learner.n_mask": MASK, "learner.batch_size": TRACES,
        "exploration.strategy": "bmc", "run.runs_dir": str(tmp_path), **overrides})


def batch(index: int, env_steps_total: int) -> TraceBatch:
    rng = np.random.default_rng(index)
    frames = rng.integers(0, 256, size=(TRACES * (STEPS + 1), SIZE, SIZE, 3), dtype=np.uint8)
    return TraceBatch(
        request_id=index, observations=FrameStack.from_array(frames),
        actions=rng.integers(0, 5, size=(TRACES, STEPS)), rewards=rng.random((TRACES, STEPS), dtype=np.float32),
        terminated=np.zeros((TRACES, STEPS), bool), weights_version=np.zeros((TRACES, STEPS), np.int64),
        env_steps_total=env_steps_total, episodes_stored=10)


def rate(env_steps: int, start: float) -> RateState:
    return example_rate(env_steps=env_steps, start_env_steps=start, batches_served=0)


def run_updates(service: LearnerService, updates: int, per_update: float, mark: int = 1_000) -> int:
    """Updates paced at exactly `per_update` env steps each, as the replay's rate limiter serves them."""
    service.on_replay_rate(rate(mark, mark))
    service.start_updates()
    steps = mark
    for index in range(updates):
        steps = mark + round((index + 1) * per_update)
        service.train_on(batch(index, steps))
    return steps - mark


@pytest.mark.parametrize("per_update", [4.0, 2.5, 6.0])
def test_per_step_bmc_observes_one_transition_per_env_step(tmp_path, per_update):
    service = LearnerService(config_with(tmp_path, **{"pace.env_steps_per_update": per_update}))
    assert service.config.exploration.bmc.observations == "per_step"
    env_steps = run_updates(service, 8, per_update)
    assert service.strategy.returns == service.bmc_observations == env_steps  # 32, 20 or 48
    assert service.strategy.returns / env_steps == 1.0
    assert service.strategy.posterior.count == env_steps


def test_per_transition_bmc_observes_every_unmasked_transition(tmp_path):
    service = LearnerService(config_with(tmp_path, **{"exploration.bmc.observations": "per_transition",
                                                      "pace.env_steps_per_update": 4.0}))
    env_steps = run_updates(service, 8, 4.0)
    assert service.strategy.returns == 8 * TRACES * (STEPS - MASK) == 48
    assert service.strategy.returns / env_steps == 1.5


def test_per_step_cannot_observe_more_than_a_batch_holds(tmp_path):
    service = LearnerService(config_with(tmp_path, **{"pace.env_steps_per_update": 20.0}))
    run_updates(service, 3, 20.0)
    assert service.strategy.returns == 3 * 6


def test_the_achieved_ratio_counts_from_the_replays_start_mark(tmp_path):
    service = LearnerService(config_with(tmp_path, **{"pace.env_steps_per_update": 4.0}))
    run_updates(service, 10, 4.0, mark=500)
    assert service.env_steps_per_update() == pytest.approx(4.0)
    service.on_replay_rate(rate(548, 500))  # 12 updates due, 10 made
    assert service.env_steps_per_update() == pytest.approx(4.8)


def test_the_run_ends_when_the_limiter_closed_it_and_the_updates_it_says_are_due_are_made():
    clock = RunClock()
    clock.observe_rate(example_rate(env_steps=980, start_env_steps=100.0, updates_due=220.0))
    assert not clock.finished(updates=300)  # not closed: the budget is not spent
    clock.observe_rate(example_rate(env_steps=1_100, start_env_steps=100.0, updates_due=250.0, closed=True))
    clock.observe_rate(example_rate(env_steps=1_020, start_env_steps=100.0, updates_due=230.0))  # late, older
    assert clock.closed and not clock.finished(updates=249)
    assert clock.finished(updates=250)  # the limiter's count, not the learner's own: 250 due, not 230
    clock.observe(5_000)  # a batch's count moves the steps, not the limiter's word
    assert clock.finished(updates=250)


def test_an_unpaced_run_ends_once_closed_without_paying_the_rest():
    clock = RunClock()
    clock.observe_rate(example_rate(env_steps=1_020, start_env_steps=100.0, updates_due=230.0, unpaced=True))
    assert not clock.finished(updates=10)
    clock.observe_rate(example_rate(env_steps=1_020, start_env_steps=100.0, updates_due=230.0, unpaced=True,
                                    closed=True))
    assert clock.finished(updates=10)


def test_the_replays_close_comes_on_both_of_its_keys_and_what_does_not_fit_is_refused(tmp_path):
    service = LearnerService(config_with(tmp_path, **{"pace.total_env_steps": 1_000}))
    service.on_replay_rate(example_rate(env_steps=1_040, start_env_steps=1_000.0, closed=True))
    assert service.clock.closed and not service.finished()  # 10 updates due, none made
    service.on_replay_stats(example_replay_stats(example_rate(env_steps=1_040, start_env_steps=1_000.0), episodes=5))
    assert not service.clock.closed and service.episodes_stored == 5
    closing = example_rate(env_steps=10**12, start_env_steps=1_000.0, closed=True)  # past budget plus buffer
    service.on_replay_rate(closing)
    service.on_replay_stats(example_replay_stats(closing))
    for wrong in (Stats(source="rate_limiter", time=0.0, values={"env_steps": 1_040, "closed": 1}),
                  example_replay_stats()):  # an older replay's untyped word; the stats on the rate's key
        service.on_replay_rate(wrong)
    service.on_replay_stats(example_rate(closed=True))
    assert not service.clock.closed and service.episodes_stored == 5
    counts = service.rejections.values()
    assert (counts["rejected_rate_values"], counts["rejected_stats_values"]) == (1, 1)
    assert (counts["rejected_rate_wrong_type"], counts["rejected_stats_wrong_type"]) == (2, 1)


def test_reports_only_move_the_count_forward_and_survive_a_checkpoint():
    clock = RunClock()
    clock.observe_rate(example_rate(env_steps=500, start_env_steps=100.0, updates_due=100.0))
    clock.observe(480)  # an older batch, answered late
    clock.observe_rate(example_rate(env_steps=490, start_env_steps=100.0, updates_due=97.5))  # an older word
    assert clock.env_steps == 500 and clock.updates_due() == 100
    again = RunClock()
    again.load_state_dict(clock.state_dict())
    assert (again.env_steps, again.start_env_steps) == (500, 100)


def test_a_learner_resumed_after_its_last_update_ends_without_waiting_for_a_batch(tmp_path):
    """A closed run whose updates are all made gets no batch from the replay: the wait for the first one must
    end by itself, or the resumed stack never ends (seen in the chaos run's closing stack)."""
    service = LearnerService(config_with(tmp_path, **{"pace.total_env_steps": 1_000,
                                                      "learner.log_period_s": 0.05}))
    service.on_replay_rate(example_rate(env_steps=1_000, start_env_steps=0.0, closed=True, batches_served=50))
    service.learner.updates = math.ceil(service.clock.updates_due())
    stop = threading.Event()
    guard = threading.Timer(20.0, stop.set)  # the wait must end before this stops it
    guard.start()

    class NoBatch:
        def next(self, stop, timeout_s):
            stop.wait(timeout_s)
            return None

    class Outputs:
        def exploration(self, strategy, force=False):
            pass

    try:
        assert service.finished() and _first_batch(service, Outputs(), NoBatch(), stop) is None
        assert not stop.is_set()
    finally:
        guard.cancel()
