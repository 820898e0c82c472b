"""The one acting core (actor/lockstep.py): what it records, when an episode ends, and that the actor, the
evaluation and the reference loop all step their simulators with it, so that training and evaluation
episodes come from the same code."""

import threading

import numpy as np
import pytest
import torch

from actor.evaluation.episodes import EpisodeJob, GreedyPolicy, evaluation_env_config, run_lockstep
from actor.lockstep import Lockstep, episode_message, network_acts, training_actions
from actor.acting import Actor
from actor.sim import make_env
from common.analysis.stats import digest_of_actions
from common.config_values import load_config
from common.network import D3RQN, load_numpy_weights, weights_to_numpy
from common.exploration.build import make_strategy
from common.wire.exploration_state import exploration_message
from common.wire.messages import Weights
from deploy import reference_loop
from deploy.tools import off_greedy_probe


class CountingEnv:
    """Frames that count the steps; terminates after `ends_after` steps."""

    def __init__(self, ends_after: int, truncates: bool = False) -> None:
        self.ends_after, self.truncates, self.steps = ends_after, truncates, 0

    def reset(self, seed=None, options=None):
        self.steps = 0
        return np.zeros((2, 2, 1), np.uint8), {"start_set": "train", "start_index": 4}

    def step(self, action):
        self.steps += 1
        over = self.steps >= self.ends_after
        info = {"start_set": "train", "start_index": 4, "collision": over and not self.truncates}
        return np.full((2, 2, 1), self.steps, np.uint8), 0.5 * action, over and not self.truncates, over and self.truncates, info


def test_an_episode_records_every_frame_action_reward_and_tag_and_how_it_ended():
    core = Lockstep([CountingEnv(3), CountingEnv(2, truncates=True)])
    core.begin(0)
    core.begin(1)
    assert core.step({0: 1, 1: 2}, tag=7) == []
    (slot, cut), = core.step({0: 2, 1: 0}, tag=8)
    assert slot == 1 and (cut.truncated, cut.terminated, cut.collided) == (True, False, False)
    (slot, ended), = core.step({0: 0}, tag=9)
    assert slot == 0 and not core.running
    assert [int(frame.flat[0]) for frame in ended.frames] == [0, 1, 2, 3]
    assert (ended.actions, ended.rewards, ended.tags) == ([1, 2, 0], [0.5, 1.0, 0.0], [7, 8, 9])
    assert (ended.terminated, ended.truncated, ended.collided, ended.length) == (True, False, True, 3)
    episode = episode_message(ended, actor_id=2, seed=5, episode_index=11, epsilon=0.1, incarnation=3)
    assert (len(episode.actions), episode.start_index, list(episode.weights_version)) == (3, 4, [7, 8, 9])
    assert episode.terminated and not episode.truncated


def test_max_steps_cuts_an_episode_and_an_evaluation_keeps_only_the_latest_frame():
    core = Lockstep([CountingEnv(100)], max_steps=2, keep_frames=False)
    core.begin(0)
    core.step({0: 1})
    (_, cut), = core.step({0: 1})
    assert (cut.length, cut.truncated, cut.terminated) == (2, True, False)
    assert len(cut.frames) == 1 and int(cut.observation.flat[0]) == 2


def greedy_config():
    # no start jitter: a start pose and the actions fix the episode, whichever seed the reset draws with
    return load_config("smoke", overrides={
        "network.lstm_units": 16, "env.max_steps": 60, "evaluation.max_steps": 60, "env.start_jitter_m": 0.0,
        "env.start_jitter_deg": 0.0, "exploration.strategy": "constant", "exploration.constant.epsilon": 0.0})


def test_a_training_episode_and_an_evaluation_episode_from_one_start_are_the_same_episode():
    config = greedy_config()
    torch.manual_seed(0)
    tensors = weights_to_numpy(D3RQN(config.network))
    actor = Actor(config, 0)
    strategy = make_strategy(config.exploration, config.network.n_actions)
    strategy.start()
    actor.mailbox.offer_weights(Weights(version=1, tensors=tensors))
    actor.mailbox.offer_exploration(exploration_message(strategy))
    actor.apply_mail()
    trained = [actor.run_episode(threading.Event())[0] for _ in range(6)]

    network = D3RQN(config.network)
    load_numpy_weights(network, tensors)
    jobs = [EpisodeJob("greedy", "train", episode.start_index, 0, seed=123) for episode in trained]
    evaluated = []
    run_lockstep(jobs, [make_env(evaluation_env_config(config)) for _ in range(2)],
                 {"greedy": GreedyPolicy(network.eval(), 2)}, config.evaluation.max_steps,
                 config.evaluation.reward_bins, evaluated.append)
    by_start = {episode.start_index: episode for episode in evaluated}
    assert len({len(episode.actions) for episode in trained}) > 1  # the policy's choices told episodes apart
    for episode in trained:
        again = by_start[episode.start_index]
        assert again.length == len(episode.actions)
        assert again.actions_digest == digest_of_actions(episode.actions.tolist())
        assert again.episode_return == pytest.approx(float(episode.rewards.sum()))


def test_the_actor_the_evaluation_and_the_reference_loop_all_step_on_the_core(monkeypatch):
    stepped: list[int] = []
    original = Lockstep.step

    def counted(self, actions, tag=-1):
        stepped.append(len(actions))
        return original(self, actions, tag)

    monkeypatch.setattr(Lockstep, "step", counted)
    config = greedy_config()
    actor = Actor(config, 0)
    actor.run_episode(threading.Event())
    by_actor, stepped[:] = len(stepped), []
    network = D3RQN(config.network).eval()
    run_lockstep([EpisodeJob("greedy", "test", 0, 0, seed=1)],
                 [make_env(evaluation_env_config(config))],
                 {"greedy": GreedyPolicy(network, 1)}, 20, config.evaluation.reward_bins, lambda episode: None)
    by_evaluation, stepped[:] = len(stepped), []
    loop = reference_loop.train(load_config("smoke", overrides={"pace.total_env_steps": 30,
                                                                "network.lstm_units": 16}), evaluate_at_end=False)
    assert by_actor > 0 and by_evaluation > 0
    assert len(stepped) == loop.env_steps


def test_the_acting_rule_is_uniform_until_the_network_acts_then_the_strategys():
    config = greedy_config()
    strategy = make_strategy(config.exploration, 5)
    draws = training_actions(strategy, None, [np.random.default_rng(seed) for seed in (1, 2)], 5)
    assert draws == [int(np.random.default_rng(seed).integers(5)) for seed in (1, 2)]  # each its own generator
    strategy.start()  # constant epsilon 0: greedy from here
    rows = np.array([[0.0, 3.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 9.0]])
    assert training_actions(strategy, rows, [np.random.default_rng(0)] * 2, 5) == [1, 4]


def test_the_network_acts_once_the_learners_strategy_started_and_its_weights_came():
    strategy = make_strategy(greedy_config().exploration, 5)
    assert not network_acts(None, 3)  # no strategy came from the learner yet
    assert not network_acts(strategy, 3)  # updates have not started
    strategy.start()
    assert not network_acts(strategy, -1) and network_acts(strategy, 0)


def test_the_reference_loop_acts_by_the_actors_rule_and_the_probe_on_the_core(monkeypatch):
    import deploy.reference_loop as loop_module
    calls, stepped = [], []
    monkeypatch.setattr(loop_module, "training_actions", lambda *args: calls.append(args) or training_actions(*args))
    asked = []
    monkeypatch.setattr(loop_module, "network_acts", lambda *args: asked.append(args) or network_acts(*args))
    original = Lockstep.step
    monkeypatch.setattr(Lockstep, "step", lambda self, actions, tag=-1: stepped.append(1) or original(self, actions, tag))
    loop = reference_loop.train(load_config("smoke", overrides={"pace.total_env_steps": 30,
                                                                "network.lstm_units": 16}), evaluate_at_end=False)
    assert len(calls) == len(asked) == loop.env_steps
    stepped[:] = []
    config = greedy_config()
    rows = off_greedy_probe.greedy_q_rows(config, weights_to_numpy(D3RQN(config.network)), 1, 3)
    assert len(stepped) == len(rows) == 3
