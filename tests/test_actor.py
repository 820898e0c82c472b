import threading

import numpy as np

from common.config import load_config
from common.exploration import exploration_message
from common.network import D3RQN, weights_to_numpy
from common.wire import Stats, Weights
from actor.runner import Actor, Mailbox, actor_seed


def small_config():
    return load_config("smoke", overrides={"network.lstm_units": 16, "env.max_steps": 25,
                                           "exploration.strategy": "constant"})


def test_seeds_differ_per_actor_and_repeat_per_run():
    assert actor_seed(0, 1) == actor_seed(0, 1)
    assert len({actor_seed(0, actor_id) for actor_id in range(8)} | {actor_seed(1, 0)}) == 9


def test_mailbox_keeps_only_the_newest_weights():
    mailbox = Mailbox()
    for version in (3, 5, 4):
        mailbox.offer_weights(Weights(version=version, tensors={}))
    weights, exploration = mailbox.take()
    assert weights.version == 5 and exploration is None
    assert mailbox.take() == (None, None)


def test_actor_waits_only_while_the_learner_lags_beyond_the_tolerance():
    mailbox = Mailbox()
    assert not mailbox.learner_lags(0.1)  # no learner heard of: never hold
    progress = lambda updates, due: mailbox.offer_progress(
        Stats(source="learner", time=0.0, values={"updates": updates, "updates_due": due, "env_steps": 0}))
    progress(95, 100)
    assert not mailbox.learner_lags(0.1)  # 5 behind, 10 allowed
    progress(89, 100)
    assert mailbox.learner_lags(0.1)
    progress(0, 1)
    assert not mailbox.learner_lags(0.0)  # at least one update of slack


def test_episode_before_and_after_weights_and_start():
    config = small_config()
    actor = Actor(config, actor_id=2)
    stop = threading.Event()
    episode, record = actor.run_episode(stop)
    steps = len(episode.actions)
    assert len(episode.observations) == steps + 1 and 1 <= steps <= 25
    assert (episode.weights_version == -1).all() and episode.epsilon == 1.0
    assert episode.terminated != episode.truncated
    assert record.length == steps and np.isclose(record.episode_return, episode.rewards.sum())

    # The learner's weights and a started strategy arrive through the mailbox.
    network = D3RQN(config.network)
    actor.mailbox.offer_weights(Weights(version=7, tensors=weights_to_numpy(network)))
    learner_side = Actor(config, actor_id=99).strategy
    learner_side.start()
    actor.mailbox.offer_exploration(exploration_message(learner_side))
    episode, record = actor.run_episode(stop)
    assert (episode.weights_version == 7).all()
    assert episode.epsilon == config.exploration.constant.epsilon and actor.uses_network()
    assert record.episode_index == 1
