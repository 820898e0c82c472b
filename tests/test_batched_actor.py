"""An actor stepping several simulators in lockstep (actor.envs_per_actor): each with its own seed, LSTM
state, exploration draws and episodes, and the replay takes them as it takes a single-env actor's."""

import threading

import numpy as np
import pytest
import torch

from actor.batched_q import BatchedQ
from actor.delivery import Outbox
from actor.gate import EpisodeGate, HoldLog
from actor.acting import Actor, actor_seed, env_seed
from actor.runner import ReplayWatch, _drive
from actor.sim import make_env
from common.config_values import load_config
from common.exploration.build import make_strategy
from common.wire.exploration_state import exploration_message
from common.network import D3RQN, load_numpy_weights, weights_to_numpy
from common.schema.fields import ConfigError
from common.wire.envelope import decode, encode
from common.wire.messages import Episode, Weights
from replay.service import ReplayService
from wire_examples import example_rate


def config_with(envs: int, tmp_path=None, **overrides):
    values = {"network.lstm_units": 16, "env.max_steps": 25, "exploration.strategy": "max_boltzmann",
              "actor.envs_per_actor": envs, **overrides}
    if tmp_path is not None:
        values["run.runs_dir"] = str(tmp_path)
    return load_config("smoke", overrides=values)


def weights(config) -> dict[str, np.ndarray]:
    torch.manual_seed(0)
    return weights_to_numpy(D3RQN(config.network))


def started_strategy(config):
    strategy = make_strategy(config.exploration, config.network.n_actions)
    strategy.start()
    return strategy


def acting_with_the_network(actor: Actor, tensors) -> Actor:
    """The learner's weights and started strategy, as they arrive through the mailbox."""
    actor.mailbox.offer_weights(Weights(version=3, tensors=tensors))
    actor.mailbox.offer_exploration(exploration_message(started_strategy(actor.config)))
    actor.apply_mail()
    assert actor.uses_network()
    return actor


class Records(list):
    """Stands in for the actor's link to the hub (common/hub_link.py): keeps the episode records it is given."""

    def put(self, name, message) -> None:
        assert name == "records"
        self.append(message)


def test_envs_per_actor_must_be_positive():
    with pytest.raises(ConfigError, match="envs_per_actor"):
        config_with(0)


def test_each_env_seed_derives_from_the_actors_seed_and_its_index():
    seed = actor_seed(0, 4)
    assert env_seed(seed, 0) == seed  # one env per actor: the single-env actor's seed
    seeds = [env_seed(seed, index) for index in range(8)]
    assert seeds == [env_seed(seed, index) for index in range(8)] and len(set(seeds)) == 8
    assert env_seed(actor_seed(1, 4), 1) not in seeds
    actor = Actor(config_with(3), actor_id=4)
    assert [slot.seed for slot in actor.slots] == seeds[:3]


def single_env_episodes(config, actor_id: int, tensors, random_episodes: int, network_episodes: int):
    """The single-env actor's loop written out as it was before actor.envs_per_actor: one simulator and one
    generator from the actor's seed, the LSTM state from zero each episode, one frame per forward pass."""
    seed = actor_seed(config.run.seed, actor_id)
    env, rng = make_env(config.env, seed=seed), np.random.default_rng(seed)
    network = D3RQN(config.network).eval()
    load_numpy_weights(network, tensors)
    strategy = started_strategy(config)
    episodes = []
    for uses_network in [False] * random_episodes + [True] * network_episodes:
        observation, _ = env.reset(options={"start_set": "train"})
        state = network.initial_state(1)
        frames, actions, rewards = [observation], [], []
        terminated = truncated = False
        while not (terminated or truncated):
            if uses_network:
                with torch.inference_mode():
                    q_values, state = network(torch.from_numpy(observation).view(1, 1, *observation.shape), state)
                action = strategy.act(q_values[0, 0].numpy(), rng)
            else:
                action = int(rng.integers(config.network.n_actions))
            observation, reward, terminated, truncated, _ = env.step(action)
            frames.append(observation)
            actions.append(action)
            rewards.append(float(reward))
        episodes.append((np.stack(frames), actions, rewards))
    return episodes


def test_one_env_per_actor_drives_the_episodes_of_the_single_env_actor():
    config = config_with(1)
    tensors = weights(config)
    expected = single_env_episodes(config, 2, tensors, random_episodes=2, network_episodes=4)
    actor, stop = Actor(config, actor_id=2), threading.Event()
    episodes = [actor.run_episode(stop)[0] for _ in range(2)]
    acting_with_the_network(actor, tensors)
    episodes += [actor.run_episode(stop)[0] for _ in range(4)]
    assert any(len(set(actions)) > 1 for _, actions, _ in expected[2:])  # exploration drew from the generator
    for episode, (frames, actions, rewards) in zip(episodes, expected):
        assert episode.actions.tolist() == actions and episode.rewards.tolist() == np.float32(rewards).tolist()
        assert np.array_equal(episode.observations.decode(), frames)
        assert episode.seed == actor.seed
    assert [episode.episode_index for episode in episodes] == list(range(6))


def test_batched_q_values_equal_one_forward_pass_per_env():
    config = config_with(3)
    network = D3RQN(config.network).eval()
    load_numpy_weights(network, weights(config))
    batched = BatchedQ(network, 3)
    rng = np.random.default_rng(0)
    shape = (config.network.frame_height, config.network.frame_width, config.network.frame_channels)
    states = [network.initial_state(1) for _ in range(3)]
    for step in range(4):
        slots = [0, 1, 2] if step != 2 else [2, 0]  # a step in which env 1 does not run
        frames = [rng.integers(0, 256, shape, dtype=np.uint8) for _ in slots]
        got = batched.q_values(slots, frames)
        for row, slot, frame in zip(got, slots, frames):
            with torch.inference_mode():
                single, states[slot] = network(torch.from_numpy(frame)[None, None], states[slot])
            assert torch.allclose(row, single[0, 0], atol=1e-5)
    assert batched.hidden[0, 1].abs().sum() > 0
    batched.reset(1)
    assert batched.hidden[0, 1].abs().sum() == 0 and batched.cell[0, 1].abs().sum() == 0
    assert torch.allclose(batched.hidden[0, [0, 2]], torch.cat([states[0][0][0], states[2][0][0]]))


def test_three_envs_give_well_formed_episodes_from_each_that_the_replay_takes(tmp_path):
    config = config_with(3, tmp_path)
    actor = acting_with_the_network(Actor(config, actor_id=1), weights(config))
    seen = {slot.index: [] for slot in actor.slots}  # every env's Q-values, step after step
    q_values = actor.batched_q.q_values

    def recording(slots, observations):
        rows = q_values(slots, observations)
        for slot, row in zip(slots, rows):
            seen[slot].append(row.clone())
        return rows

    actor.batched_q.q_values = recording
    outbox, records = Outbox(max_episodes=100, max_bytes=10**10), Records()
    _drive(actor, threading.Event(), 9, outbox, records)
    episodes = [decode(encode(episode), Episode) for episode, _ in outbox._queue]

    assert [episode.episode_index for episode in episodes] == list(range(9)) == [r.episode_index for r in records]
    assert actor.episodes_started == 9 and not actor.running
    by_env = {slot.seed: [e for e in episodes if e.seed == slot.seed] for slot in actor.slots}
    assert len(by_env) == 3 and all(by_env.values())  # every env, each with its own seed
    assert {e.in_hand for e in episodes} == {3 + config.actor.queue_episodes}  # for the replay's hold guard
    replay = ReplayService(config)
    for episode in episodes:
        replay.on_episode(episode)
    assert replay.rejections.total == 0 and replay.ledger.missing == 0 and replay.ledger.duplicates == 0
    assert replay.store.env_steps_total == sum(len(e) for e in episodes) == sum(r.length for r in records)

    # Each env's LSTM state starts from zero with each of its episodes and runs on through it: the Q-values
    # it acted on are those of one forward pass over that episode's frames alone.
    reference = D3RQN(config.network).eval()
    load_numpy_weights(reference, weights(config))
    for slot in actor.slots:
        rows = torch.stack(seen[slot.index])
        assert len(rows) == sum(len(e) for e in by_env[slot.seed])
        for episode in by_env[slot.seed]:
            frames = torch.from_numpy(episode.observations.decode(0, len(episode)))[None]
            with torch.inference_mode():
                expected = reference(frames)[0][0]
            assert torch.allclose(rows[:len(episode)], expected, atol=1e-5)
            rows = rows[len(episode):]


def test_a_held_env_waits_while_the_others_finish_their_episodes():
    actor = Actor(config_with(3), actor_id=0)
    gate = EpisodeGate(actor.mailbox, HoldLog(10.0), lambda: True)
    rate = lambda reason: actor.mailbox.offer_rate(example_rate(hold_reason=reason))
    assert actor.step(gate) == [] and len(actor.running) == 3
    rate("behind")
    ended = []
    for _ in range(30):  # episodes last at most env.max_steps = 25 steps
        ended += actor.step(gate)
    assert not actor.running and actor.episodes_started == 3
    assert sorted(episode.seed for episode, _ in ended) == sorted(slot.seed for slot in actor.slots)
    rate("")
    actor.step(gate)
    assert actor.episodes_started == 6


def test_while_no_replay_is_alive_no_episode_begins_until_a_replays_word_comes_again():
    # a killed replay's rate limiter counts nothing: episodes begun meanwhile would run past the ratio
    actor = Actor(config_with(1), actor_id=0)
    gate = EpisodeGate(actor.mailbox, HoldLog(10.0), lambda: True)
    watch = ReplayWatch(actor.mailbox.replay_gone)
    go = example_rate()
    watch.on_change("replay/a", True)
    actor.mailbox.offer_rate(go)
    assert gate()
    watch.on_change("replay/b", True)
    watch.on_change("replay/a", False)
    assert watch.alive and gate()  # another replay is still there
    watch.on_change("replay/b", False)
    assert not watch.alive and not gate() and actor.mailbox.must_hold() == "replay"
    watch.on_change("replay/c", True)
    assert not gate()  # alive again, but its limiter has not spoken
    actor.mailbox.offer_rate(go)
    assert gate()


def test_once_updates_have_started_an_actor_without_the_learners_policy_starts_no_episode():
    # a resumed run or a restarted actor: acting at random would fill the replay with episodes of no policy
    actor = Actor(config_with(2), actor_id=0)
    gate = EpisodeGate(actor.mailbox, HoldLog(10.0), lambda: True, actor.uses_network)
    rate = lambda **changes: actor.mailbox.offer_rate(example_rate(**changes))
    rate(start_env_steps=None, batches_served=0)  # stage 1: random episodes are what the run wants
    assert gate() and actor.mailbox.must_hold(False) == ""
    rate(start_env_steps=500.0, refilling=True)  # a resumed replay refilling its lost store: stage 1 again
    assert gate()
    rate(start_env_steps=500.0, refilling=False)
    assert not gate() and actor.mailbox.must_hold(False) == "policy"
    actor.mailbox.offer_weights(Weights(version=7, tensors={name: tensor.numpy() for name, tensor
                                                             in actor.network.state_dict().items()}))
    actor.mailbox.offer_exploration(exploration_message(started_strategy(actor.config)))  # the learner's: started
    actor.apply_mail()
    assert actor.uses_network() and gate()

