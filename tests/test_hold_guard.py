"""The replay refuses episodes an actor began while told to hold (replay/hold_guard.py): past the grace
(actor.silence_hold_s plus two stats periods), an actor's episodes beyond its allowance past the
highest index it had delivered are refused, refused again when sent again, and leave no gap in the
ledger; what it had in hand is taken, and nothing is refused while the actors may go."""

import dataclasses

from common.config_values import load_config
from fake_clock import FakeClock
from replay.hold_guard import HoldGuard
from replay.service import ReplayService
from tests.test_delivery import words
from tests.test_hostile_input import STEPS, episode, small_config


def test_the_grace_and_the_allowance_come_from_the_runs_config():
    guard = HoldGuard.of(load_config("smoke", overrides={"actor.silence_hold_s": 30.0, "replay.stats_period_s": 0.5,
                                                         "actor.envs_per_actor": 3, "actor.queue_episodes": 5}))
    assert (guard.grace_s, guard.allowance) == (31.0, 16)


def test_past_the_grace_only_what_the_actor_had_in_hand_is_taken():
    clock = FakeClock(10.0)
    guard = HoldGuard(grace_s=30.0, allowance=2, clock=clock)
    assert all(guard.admits(1, 7, index, index - 1) for index in range(5))  # nobody held
    guard.note_hold(True)
    clock.now += 29.0
    assert guard.admits(1, 7, 5, 4)  # within the grace: the word may be on its way
    clock.now += 2.0
    guard.note_hold(True)  # still the same hold
    assert guard.admits(1, 7, 6, 5) and guard.admits(1, 7, 7, 6)  # its mark is 5: two more in hand
    assert not guard.admits(1, 7, 8, 7) and not guard.admits(1, 7, 8, 7)  # refused, and again when resent
    assert guard.admits(1, 7, 3, 7)  # an older one sent again: the ledger says duplicate
    assert guard.admits(2, 9, 0, -1) and guard.admits(2, 9, 1, 0) and not guard.admits(2, 9, 2, 1)  # a new one
    assert guard.admits(1, 0, 99, -1)  # no incarnation (an older sender): not named, never refused
    guard.note_hold(False)
    assert guard.admits(1, 7, 9, 7) and not guard.admits(1, 7, 8, 9)  # the go: new ones taken, a refused one never
    assert guard.refused == 4



def test_an_actor_that_states_more_in_hand_than_the_runs_config_is_allowed_twice_that():
    # A remote actor started with more simulators than the run's config (actor.envs_per_actor on its host)
    clock = FakeClock(10.0)
    guard = HoldGuard(grace_s=0.0, allowance=2, clock=clock)
    guard.note_hold(True)
    assert guard.admits(1, 7, 5, 4, in_hand=3) and guard.admits(1, 7, 10, 9, in_hand=3)  # mark 4, 2 x 3 more
    assert not guard.admits(1, 7, 11, 10, in_hand=3)
    assert guard.admits(2, 9, 6, 4, in_hand=1) and not guard.admits(2, 9, 7, 6, in_hand=1)  # the config's 2 at least
    assert guard.admits(3, 5, 8_196, 4, in_hand=10**12) and not guard.admits(3, 5, 8_197, 8_196, in_hand=10**12)

def test_the_replay_refuses_an_actor_that_drives_on_while_held(tmp_path):
    service = ReplayService(small_config(tmp_path, **{"pace.start_episodes": 2}))
    service.hold_guard = HoldGuard(grace_s=0.0, allowance=2, clock=FakeClock())
    index = 0
    while service.limiter.hold_reason() != "behind":  # no learner: the steps owe updates nobody makes
        service.on_episode(episode(index))
        index += 1
    words(service.acks)
    stored = len(service.store)
    for sent in range(index, index + 5):
        service.on_episode(episode(sent))
    service.on_episode(episode(index + 3))  # sent again
    assert words(service.acks) == {"received": [index, index + 1], "refused": [index + 2, index + 3, index + 3,
                                                                               index + 4]}
    assert len(service.store) == stored + 2 and service.limiter.env_steps == (stored + 2) * STEPS
    assert service.ledger.missing == 0 and service.hold_guard.refused == 4
    assert service.rejections.values()["rejected_episode_begun_while_held"] == 4
    stating = dataclasses.replace(episode(index + 5), in_hand=3)  # its mark is index - 1: six in its hands
    service.on_episode(stating)
    assert words(service.acks) == {"received": [index + 5]}
