"""The reference loop trains on the smoke preset with every strategy, calling every hook the stack calls."""

import collections
import math

import numpy as np
import pytest
import torch

from common.config_values import load_config
from common.exploration.bmc import bmc_observation_count
from common.exploration.names import STRATEGIES
from deploy import reference_loop

HOOKS = ("start", "act", "on_env_steps", "on_update", "on_returns")
BUDGET = 300  # env steps: two random episodes, then about 13 updates at the smoke preset's 20 steps per update


def spy_on(strategy) -> collections.Counter:
    """Counts the calls of each hook on this instance (and BMC's observations per call)."""
    calls = collections.Counter()
    calls["observations"] = []
    for name in HOOKS:
        method = getattr(strategy, name)

        def counted(*args, _method=method, _name=name, **kwargs):
            calls[_name] += 1
            if _name == "on_returns":
                calls["observations"].append(np.size(args[0]))
            return _method(*args, **kwargs)

        setattr(strategy, name, counted)
    return calls


@pytest.fixture
def spied(monkeypatch):
    """The strategies the loop builds, each with its call counter."""
    built = []
    make_strategy = reference_loop.make_strategy

    def spying(config, n_actions):
        strategy = make_strategy(config, n_actions)
        built.append((strategy, spy_on(strategy)))
        return strategy

    monkeypatch.setattr(reference_loop, "make_strategy", spying)
    torch.set_num_threads(1)
    return built


def smoke(strategy: str, **overrides):
    """The smoke preset, with a narrower LSTM so that seven trainings take seconds (the command test
    below runs the preset's own network)."""
    return load_config("smoke", overrides={"exploration.strategy": strategy, "pace.total_env_steps": BUDGET,
                                           "network.lstm_units": 64, **overrides})


@pytest.mark.parametrize("name", STRATEGIES)
def test_the_loop_trains_and_feeds_every_hook_of_the_strategy(name, spied):
    config = smoke(name)
    result = reference_loop.train(config, evaluate_at_end=False, log_period_s=1e9)
    ((strategy, calls),) = spied
    per_update = config.pace.env_steps_per_update

    assert result.env_steps >= BUDGET and result.episodes >= 3
    if name == "decreasing":  # starts at pace.start_steps env steps, the others at start_episodes episodes
        assert result.start_env_steps == config.pace.start_steps
    else:
        assert result.start_env_steps < config.pace.start_steps
    assert result.updates == math.ceil((result.env_steps - result.start_env_steps) / per_update) >= 8
    assert math.isfinite(result.loss)

    # the actor's side: one start, at the end of the episode that set the start mark, then the strategy's
    # rule at every step after it (by steps, the mark is start_steps, inside that episode)
    assert calls["start"] == 1 and strategy.started
    if name == "decreasing":
        assert 0 <= result.env_steps - calls["act"] - result.start_env_steps < config.env.max_steps
    else:
        assert calls["act"] == result.env_steps - result.start_env_steps
    # the learner's side, once per update, as learner/service.py calls them
    assert calls["on_env_steps"] == result.updates
    # update k comes at the first step that pays for it, k - 1 periods and one step after the start
    assert strategy.env_steps == result.start_env_steps + (result.updates - 1) * per_update + 1
    assert calls["on_update"] == (result.updates if strategy.needs_q_after else 0)
    assert calls["on_returns"] == (result.updates if strategy.needs_returns else 0)
    if strategy.needs_returns:  # BMC at the authors' rate: one per env step, at most a batch's unmasked steps
        unmasked = config.learner.batch_size * (config.learner.trace_length - config.learner.n_mask)
        assert calls["observations"] == [min(bmc_observation_count(k, per_update), unmasked)
                                         for k in range(1, result.updates + 1)]
        assert strategy.posterior.count == sum(calls["observations"])
    if strategy.needs_q_after:
        assert strategy.epsilon != config.exploration.vdbe.eps0  # VDBE's epsilon moved with the updates


def test_bmc_per_transition_feeds_every_unmasked_step(spied):
    config = smoke("bmc", **{"exploration.bmc.observations": "per_transition"})
    result = reference_loop.train(config, evaluate_at_end=False, log_period_s=1e9)
    unmasked = config.learner.batch_size * (config.learner.trace_length - config.learner.n_mask)
    assert spied[0][1]["observations"] == [unmasked] * result.updates


def test_the_command_trains_then_evaluates(spied, capsys):
    reference_loop.main(["--preset", "smoke", "--pace.total_env_steps", "200", "--learner.log_period_s", "1000",
                         "--evaluation.max_steps", "20"])
    out = capsys.readouterr().out
    assert "env steps per update since updates started" in out
    assert out.count("| greedy | train |") == 1 and out.count("| greedy | test |") == 1


def test_the_loop_with_stored_states_trains_past_the_burn_in(spied, monkeypatch):
    """learner.stored_state: the loop's episodes carry the acting state, each trace starts from its row, and
    BMC observes the steps after the burn-in (2), not after n_mask (7)."""
    stored = []
    add = reference_loop.EpisodeStore.add
    monkeypatch.setattr(reference_loop.EpisodeStore, "add",
                        lambda store, episode: stored.append(episode.recurrent_state) or add(store, episode))
    config = smoke("bmc", **{"exploration.bmc.observations": "per_transition", "learner.stored_state": True,
                             "learner.burn_in": 2})
    result = reference_loop.train(config, evaluate_at_end=False, log_period_s=1e9)
    assert result.updates >= 8 and math.isfinite(result.loss)
    assert stored and all(rows.shape[1:] == (2, 64) and rows.shape[0] >= 1 for rows in stored)
    # the random phase's episodes too (the first two) store real states after their zero start, not zero rows
    assert all(not rows[0].any() and all(row.any() for row in rows[1:]) for rows in stored[:2])
    assert spied[0][1]["observations"] == [config.learner.batch_size * (config.learner.trace_length - 2)] * result.updates


def test_the_acting_weights_catch_up_by_the_learners_broadcast_rule(spied, monkeypatch):
    """The loop's acting weights are those of the learner's broadcasts (learner/service.py Cadence), by updates
    only: each step is tagged with the update of the last broadcast, never one the rule did not send."""
    sent, episodes = [0], []
    cadence, message = reference_loop.Cadence, reference_loop.episode_message

    class Recorded(cadence):
        def due(self, updates):
            answer = super().due(updates)
            if answer:
                sent.append(updates)
            return answer

    monkeypatch.setattr(reference_loop, "Cadence", Recorded)
    monkeypatch.setattr(reference_loop, "episode_message", lambda *a, **k: episodes.append(message(*a, **k))
                        or episodes[-1])
    result = reference_loop.train(smoke("constant", **{"learner.weights_every": 3}), evaluate_at_end=False,
                                  log_period_s=1e9)
    tags = {int(tag) for episode in episodes for tag in episode.weights_version}
    assert sent[1:] == list(range(3, result.updates + 1, 3))  # by updates only, every third
    assert -1 in tags and len(tags - {-1}) >= 3 and tags - {-1} <= set(sent)
