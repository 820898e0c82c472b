"""The actor's bfloat16 forward pass (actor.inference): the float32 pass's function within bfloat16's rounding,
state kept per slot, weights refreshed on load, "auto" choosing by the timing it measures, and both
falling back or refusing where the CPU cannot run bfloat16. The tests that run the bfloat16 pass skip, with
the reason, on such a CPU; the fallback tests run everywhere, with the probe made to report bfloat16 absent."""

import numpy as np
import pytest
import torch

import actor.batched_q as batched_q_module
from actor.batched_q import BatchedQ, choose_precision
from actor.acting import Actor
from common import cpu_capability
from common.config_values import load_config
from common.exploration.build import make_strategy
from common.wire.exploration_state import exploration_message
from common.network import D3RQN, weights_to_numpy
from common.schema.fields import ConfigError
from common.wire.messages import Weights
from tests.cpu_support import needs_bfloat16

SLOTS = 4


def smoke_config(**overrides):
    return load_config("smoke", overrides={"network.lstm_units": 32, "env.max_steps": 25, **overrides})


def tensors(config, seed: int) -> dict[str, np.ndarray]:
    torch.manual_seed(seed)
    return weights_to_numpy(D3RQN(config.network))


def pair(config, seed: int = 0) -> tuple[BatchedQ, BatchedQ]:
    """A float32 and a bfloat16 BatchedQ holding the same weights."""
    made = []
    for precision in ("float32", "bfloat16"):
        batched = BatchedQ(D3RQN(config.network), SLOTS, precision)
        batched.load_weights(tensors(config, seed))
        made.append(batched)
    return made[0], made[1]


def frames(config, rng, count: int) -> list[np.ndarray]:
    shape = (config.network.frame_height, config.network.frame_width, config.network.frame_channels)
    return [rng.integers(0, 256, shape, dtype=np.uint8) for _ in range(count)]


def relative_error(got: torch.Tensor, expected: torch.Tensor) -> float:
    return float((got - expected).abs().max() / expected.abs().max())


@needs_bfloat16
def test_bfloat16_steps_follow_float32_within_rounding_with_a_state_per_slot():
    config = smoke_config()
    exact, compact = pair(config)
    rng = np.random.default_rng(1)
    schedule = [[0, 1, 2, 3], [3, 1], [0, 1, 2, 3], [2], [0, 1, 2, 3], [0, 1, 2, 3]]
    for step, slots in enumerate(schedule):
        observations = frames(config, rng, len(slots))
        expected, got = exact.q_values(slots, observations), compact.q_values(slots, observations)
        # bfloat16 keeps 8 bits of mantissa: about 0.4% per rounding, a few roundings deep.
        assert relative_error(got, expected) < 0.03, step
        assert got.dtype == torch.float32 and compact.hidden.dtype == torch.float32
        if step == 3:
            exact.reset(1), compact.reset(1)
    assert relative_error(compact.hidden, exact.hidden) < 0.03
    assert relative_error(compact.cell, exact.cell) < 0.03
    assert compact.hidden[0, 1].abs().sum() > 0  # slot 1 ran again after its reset


@needs_bfloat16
def test_bfloat16_greedy_actions_agree_with_float32_on_nearly_all_frames():
    config = smoke_config()
    exact, compact = pair(config, seed=2)
    rng = np.random.default_rng(3)
    agree = total = 0
    for _ in range(25):
        slots = list(range(SLOTS))
        observations = frames(config, rng, SLOTS)
        agree += int((exact.q_values(slots, observations).argmax(1)
                      == compact.q_values(slots, observations).argmax(1)).sum())
        total += SLOTS
    assert agree / total >= 0.9


@needs_bfloat16
def test_loading_weights_replaces_the_bfloat16_copies():
    config = smoke_config()
    exact, compact = pair(config, seed=0)
    for batched in (exact, compact):
        batched.load_weights(tensors(config, seed=5))
    observations = frames(config, np.random.default_rng(4), SLOTS)
    expected = exact.q_values(list(range(SLOTS)), observations)
    assert relative_error(compact.q_values(list(range(SLOTS)), observations), expected) < 0.03


@needs_bfloat16
def test_refused_weights_change_neither_copy():
    config = smoke_config()
    _, compact = pair(config)
    observations = frames(config, np.random.default_rng(6), SLOTS)
    before = BatchedQ(compact.network, SLOTS, "bfloat16").q_values(list(range(SLOTS)), observations)
    broken = tensors(config, seed=7)
    broken["lstm.weight_ih_l0"][0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        compact.load_weights(broken)
    assert torch.equal(compact.q_values(list(range(SLOTS)), observations), before)


def test_auto_takes_bfloat16_only_when_it_times_clearly_faster(monkeypatch):
    network = D3RQN(smoke_config().network)
    monkeypatch.setattr(cpu_capability, "bfloat16_problem", lambda: None)  # this test is about the timing
    timings = {}
    monkeypatch.setattr(batched_q_module, "step_seconds", lambda net, slots, precision: timings[precision])
    timings.update(float32=1.0, bfloat16=0.4)
    assert choose_precision(network, SLOTS, "auto") == "bfloat16"
    timings.update(float32=1.0, bfloat16=0.9)  # faster, but within the margin
    assert choose_precision(network, SLOTS, "auto") == "float32"
    timings.update(float32=1.0, bfloat16=2.2)  # a CPU without bfloat16 units
    assert choose_precision(network, SLOTS, "auto") == "float32"
    for precision in ("float32", "bfloat16"):
        assert choose_precision(network, SLOTS, precision) == precision
    with pytest.raises(ValueError, match="float32, bfloat16, auto"):
        choose_precision(network, SLOTS, "int8")


@needs_bfloat16
def test_step_seconds_times_each_precision():
    network = D3RQN(smoke_config().network)
    for precision in ("float32", "bfloat16"):
        assert 0 < batched_q_module.step_seconds(network, 2, precision, rounds=2) < 5


@needs_bfloat16
def test_an_actor_configured_for_bfloat16_acts_with_the_compact_pass():
    config = smoke_config(**{"actor.inference": "bfloat16", "actor.envs_per_actor": 2})
    actor = Actor(config, 0)
    strategy = make_strategy(config.exploration, config.network.n_actions)
    strategy.start()
    actor.mailbox.offer_weights(Weights(version=1, tensors=tensors(config, seed=0)))
    actor.mailbox.offer_exploration(exploration_message(strategy))
    actor.apply_mail()
    assert actor.uses_network() and actor.batched_q.precision == "bfloat16"
    exact = BatchedQ(D3RQN(config.network), 2)
    exact.load_weights(tensors(config, seed=0))
    observations = frames(config, np.random.default_rng(8), 2)
    assert relative_error(actor.batched_q.q_values([0, 1], observations), exact.q_values([0, 1], observations)) < 0.03
    episodes = []
    while len(episodes) < 3:
        episodes += actor.step()
    assert all(len(episode.actions) >= 1 for episode, _ in episodes)


def test_an_unknown_inference_precision_is_a_config_error():
    with pytest.raises(ConfigError, match="inference"):
        smoke_config(**{"actor.inference": "int8"})


ABSENT = "this CPU (a test's) lacks the avx512bw+avx512vl+avx512dq or avx_ne_convert instructions"


def test_auto_falls_back_to_float32_with_one_log_line_where_bfloat16_cannot_run(monkeypatch, caplog):
    monkeypatch.setattr(cpu_capability, "bfloat16_problem", lambda: ABSENT)
    monkeypatch.setattr(batched_q_module, "step_seconds", lambda *_: pytest.fail("auto timed a precision"))
    with caplog.at_level("INFO", logger="actor"):
        assert choose_precision(D3RQN(smoke_config().network), SLOTS, "auto") == "float32"
    said = [record.getMessage() for record in caplog.records]
    assert len(said) == 1 and "actor.inference auto: float32" in said[0] and ABSENT in said[0]


def test_an_actor_configured_auto_acts_in_float32_where_bfloat16_cannot_run(monkeypatch):
    monkeypatch.setattr(cpu_capability, "bfloat16_problem", lambda: ABSENT)
    actor = Actor(smoke_config(**{"actor.inference": "auto", "actor.envs_per_actor": 2}), 0)
    assert actor.batched_q.precision == "float32"


def test_an_explicit_bfloat16_is_refused_where_it_cannot_run(monkeypatch):
    monkeypatch.setattr(cpu_capability, "bfloat16_problem", lambda: ABSENT)
    network = D3RQN(smoke_config().network)
    with pytest.raises(cpu_capability.PrecisionUnavailable, match=r"^actor.inference = bfloat16 cannot run here: "
                                                                  r"this CPU \(a test's\) lacks"):
        choose_precision(network, SLOTS, "bfloat16")
    assert choose_precision(network, SLOTS, "float32") == "float32"
