import dataclasses
import logging
import threading

import numpy as np
import torch

from actor.delivery import Outbox
from actor.mailbox import Mailbox
from actor.acting import Actor, actor_seed
from actor.runner import _stats
from common.config_values import load_config
from common.exploration.build import make_strategy
from common.exploration.base import Counters
from common.exploration.vdbe import VdbeState
from common.wire.exploration_state import exploration_message
from common.network import D3RQN, weights_to_numpy
from common.wire.envelope import decode, encode
from common.wire.messages import Stats, Weights
from common.wire.metrics import ActorStats
from wire_examples import example_rate
from learner.update import DoubleQLearner


def small_config():
    return load_config("smoke", overrides={"network.lstm_units": 16, "env.max_steps": 25,
                                           "exploration.strategy": "constant"})


def test_seeds_differ_per_actor_and_repeat_per_run():
    assert actor_seed(0, 1) == actor_seed(0, 1)
    assert len({actor_seed(0, actor_id) for actor_id in range(8)} | {actor_seed(1, 0)}) == 9


def test_mailbox_keeps_the_last_broadcast_whatever_its_version():
    """A learner resumed from an older checkpoint broadcasts lower versions: the newest arrival wins."""
    mailbox = Mailbox()
    for version in (3, 5, 4):
        mailbox.offer_weights(Weights(version=version, tensors={}))
    weights, exploration = mailbox.take()
    assert weights.version == 4 and exploration is None
    assert mailbox.take() == (None, None)


def test_weights_replaced_unloaded_are_counted_and_staleness_is_read_from_the_replays_word():
    """Broadcasts that queue on a slow link: only the newest is loaded, the older ones are counted."""
    mailbox = Mailbox()
    assert mailbox.weights_behind(5) == 0  # the learner's updates unknown: nothing to say
    for version in (10, 20, 30):
        mailbox.offer_weights(Weights(version=version, tensors={}))
    assert mailbox.superseded == 2 and mailbox.take()[0].version == 30
    mailbox.offer_weights(Weights(version=40, tensors={}))
    assert mailbox.superseded == 2  # the loop had taken the last one
    mailbox.offer_rate(example_rate(batches_served=95))
    assert mailbox.weights_behind(30) == 65 and mailbox.weights_behind(-1) == 0 and mailbox.weights_behind(99) == 0
    mailbox.offer_rate(Stats(source="rate_limiter", time=0.0, values={"hold_reason": "", "batches_served": 5}))
    assert mailbox.weights_behind(30) == 65  # an older replay's untyped word changes nothing
    assert mailbox.rejections.values()["rejected_rate"] == 1


def test_the_start_up_answer_never_replaces_a_broadcast():
    mailbox = Mailbox()
    mailbox.offer_latest(Weights(version=2, tensors={}))
    assert mailbox.take()[0].version == 2
    mailbox.offer_weights(Weights(version=7, tensors={}))
    mailbox.offer_latest(Weights(version=9, tensors={}))  # an answer that was on its way: older than v7
    assert mailbox.take()[0].version == 7


def test_actor_holds_only_while_the_replay_says_so():
    mailbox = Mailbox()
    assert mailbox.must_hold() == ""  # no replay heard of: never hold
    rate = lambda reason: mailbox.offer_rate(example_rate(hold_reason=reason))
    rate("behind")
    assert mailbox.must_hold() == "behind"
    assert mailbox.must_hold() == "behind"  # kept, not taken
    rate("")
    assert mailbox.must_hold() == ""
    rate("budget")
    assert mailbox.must_hold() == "budget"


def test_actor_follows_the_learners_strategy_and_params(caplog):
    config = small_config()  # the actor is configured for constant epsilon
    actor = Actor(config, actor_id=1)
    learner_config = load_config("smoke", overrides={"exploration.strategy": "vdbe", "exploration.vdbe.nu": 3.0})
    learner_side = make_strategy(learner_config.exploration, config.network.n_actions)
    learner_side.start()
    learner_side.on_update(np.array([1.0, 2.0]), np.array([2.0, 0.0]))
    actor.mailbox.offer_exploration(exploration_message(learner_side))
    with caplog.at_level(logging.INFO, logger="actor"):
        actor.apply_mail()
        actor.mailbox.offer_exploration(exploration_message(learner_side))
        actor.apply_mail()  # the same strategy again: loaded, no second line
    assert actor.strategy.name == "vdbe" and actor.strategy.params()["nu"] == 3.0
    assert actor.strategy.epsilon == learner_side.epsilon < 1.0
    lines = [r.getMessage() for r in caplog.records if "following the learner" in r.getMessage()]
    assert len(lines) == 1 and "vdbe" in lines[0] and "until now" not in lines[0]  # it had none of its own
    # A state it cannot use is counted, logged and skipped: the actor keeps the learner's last strategy.
    kept = actor.strategy
    for broken in (dataclasses.replace(exploration_message(learner_side), state=VdbeState(7.0)),
                   dataclasses.replace(exploration_message(learner_side), counters=Counters(updates=-1))):
        actor.mailbox.offer_exploration(broken)
        actor.apply_mail()
    assert actor.strategy is kept and actor.strategy.epsilon == learner_side.epsilon
    assert actor.rejections.values()["rejected_exploration_invalid"] == 2
    # Another strategy replaces it, saying what it replaced.
    with caplog.at_level(logging.INFO, logger="actor"):
        actor.mailbox.offer_exploration(exploration_message(make_strategy(config.exploration, 5)))
        actor.apply_mail()
    assert actor.strategy.name == "constant" and "(until now vdbe" in caplog.records[-1].getMessage()


def test_before_the_learners_state_the_actor_has_no_strategy_and_acts_uniformly():
    """No strategy of its own: until the learner's state comes it acts uniformly at random, draw for draw as
    it does once it follows a strategy that has not started, whatever weights it holds."""
    config = small_config()
    weights = Weights(version=4, tensors=weights_to_numpy(D3RQN(config.network)))
    waiting, following = Actor(config, actor_id=6), Actor(config, actor_id=6)
    assert waiting.strategy is None
    for actor in (waiting, following):
        actor.mailbox.offer_weights(weights)
    following.mailbox.offer_exploration(exploration_message(make_strategy(config.exploration, 5)))
    stop = threading.Event()
    (episode, record), (same, _) = waiting.run_episode(stop), following.run_episode(stop)
    assert waiting.strategy is None and not waiting.uses_network() and following.strategy.name == "constant"
    np.testing.assert_array_equal(episode.actions, same.actions)
    assert (episode.weights_version == 4).all() and episode.epsilon == 1.0 and record.off_greedy == -1


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
    learner_side = make_strategy(config.exploration, config.network.n_actions)
    learner_side.start()
    actor.mailbox.offer_exploration(exploration_message(learner_side))
    episode, record = actor.run_episode(stop)
    assert (episode.weights_version == 7).all()
    assert episode.epsilon == config.exploration.constant.epsilon and actor.uses_network()
    assert record.episode_index == 1


def test_a_stored_state_actor_records_the_lstm_state_before_each_step():
    config = small_config()
    config.learner.stored_state = True
    actor = Actor(config, actor_id=3)
    network = D3RQN(config.network)
    actor.mailbox.offer_weights(Weights(version=1, tensors=weights_to_numpy(network)))
    learner_side = make_strategy(config.exploration, config.network.n_actions)
    learner_side.start()
    actor.mailbox.offer_exploration(exploration_message(learner_side))
    episode, _ = actor.run_episode(threading.Event())
    steps = len(episode.actions)
    rows = episode.recurrent_state
    assert rows.shape == (steps, 2, 16) and rows.dtype == np.float16 and steps >= 2
    assert not rows[0].any()  # an episode starts from the zero state
    frames = torch.from_numpy(episode.observations.decode()[None, :steps - 1])
    with torch.no_grad():  # the state after s_0..s_t-1 is the row of step t
        for t in range(1, steps):
            _, (hidden, cell) = network(frames[:, :t])
            np.testing.assert_allclose(rows[t, 0], hidden[0, 0].numpy(), atol=2e-3)
            np.testing.assert_allclose(rows[t, 1], cell[0, 0].numpy(), atol=2e-3, rtol=2e-3)


def test_the_random_phase_stores_the_initial_networks_real_states_and_still_acts_at_random():
    """Before the learner's first weights an actor acts uniformly; with learner.stored_state it still runs its
    network, the learner's initial one (learner.seed), so that its episodes' rows are real LSTM states, not zeros."""
    config = small_config()
    config.learner.stored_state = True
    episode, _ = Actor(config, actor_id=5).run_episode(threading.Event())
    plain, _ = Actor(small_config(), actor_id=5).run_episode(threading.Event())
    np.testing.assert_array_equal(episode.actions, plain.actions)  # the same uniform draws: the network is not asked
    assert (episode.weights_version == -1).all()
    steps = len(episode.actions)
    rows = episode.recurrent_state
    assert rows.shape == (steps, 2, 16) and not rows[0].any() and all(rows[t].any() for t in range(1, steps))
    learner_network = DoubleQLearner(config.network, config.learner).online
    frames = torch.from_numpy(episode.observations.decode()[None, :steps - 1])
    with torch.no_grad():  # the state after s_0..s_t-1 under the learner's initial weights is the row of step t
        for t in range(1, steps):
            _, (hidden, cell) = learner_network(frames[:, :t])
            np.testing.assert_allclose(rows[t, 0], hidden[0, 0].numpy(), atol=2e-3)
            np.testing.assert_allclose(rows[t, 1], cell[0, 0].numpy(), atol=2e-3, rtol=2e-3)


def test_an_actor_of_the_papers_method_records_no_state():
    episode, _ = Actor(small_config(), actor_id=4).run_episode(threading.Event())
    assert episode.recurrent_state.shape == (0, 2, 0)


def test_an_episode_counts_its_actions_that_were_not_argmax_q():
    """-1 in the random phase (no Q-values); else exactly the actions off argmax Q, whatever epsilon says."""
    config = load_config("smoke", overrides={"network.lstm_units": 16, "env.max_steps": 25,
                                             "exploration.strategy": "constant", "actor.envs_per_actor": 1})
    actor = Actor(config, actor_id=3)
    stop = threading.Event()
    assert actor.run_episode(stop)[1].off_greedy == -1
    actor.mailbox.offer_weights(Weights(version=1, tensors=weights_to_numpy(D3RQN(config.network))))
    learner_side = make_strategy(config.exploration, config.network.n_actions)
    learner_side.start()
    actor.mailbox.offer_exploration(exploration_message(learner_side))
    actor.apply_mail()
    actor.strategy.act = lambda q, rng: int((np.argmax(q) + 1) % len(q))  # never the greedy action
    record = actor.run_episode(stop)[1]
    assert record.off_greedy == record.length >= 1
    actor.strategy.act = lambda q, rng: int(np.argmax(q))
    assert actor.run_episode(stop)[1].off_greedy == 0


def test_the_actors_stats_are_its_typed_counters_with_the_run_time_ones_in_their_mapping():
    class Link:  # what _stats reads of the hub link
        reopened = 2

        def rejected(self):
            return {"weights": 3}

    actor = Actor(small_config(), actor_id=4)
    actor.rejections.reject("weights_values", "a test")
    actor.run_episode(threading.Event())
    stats = decode(encode(_stats(actor, Outbox(10, 10**9), Link())), ActorStats)
    assert (stats.episodes, stats.weights_version, stats.sessions_reopened) == (1, -1, 2)
    assert stats.rejected == {"rejected_weights_values": 1, "rejected_total": 1, "malformed_weights": 3}
