"""Hostile input for tests, door by door: random bytes, truncations, bit flips, valid messages of the
wrong type, and well-formed messages whose content does not fit the run. Deterministic (seeded)."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np

from common.config import Config
from common.exploration.build import make_strategy
from common.wire.exploration_state import exploration_message
from common.network import D3RQN, weights_to_numpy
from common.wire.codecs import Message
from common.wire.envelope import encode
from common.wire.frames import FrameStack
from common.wire.metrics import ActorStats, LearnerStats
from common.wire.messages import (Episode, EpisodeAck, EpisodeRecord, ExplorationState, RateState,
                                  ReplayStats, Stats, TraceBatch, TraceBatchRequest, Weights)
from wire_examples import example_actor_stats, example_learner_stats, example_rate, example_replay_stats

FLOOD_ACTOR = 77  # the actor id of flooded episodes


def random_payloads(rng: np.random.Generator, count: int, max_size: int = 2000) -> list[bytes]:
    return [rng.integers(0, 256, int(rng.integers(0, max_size)), dtype=np.uint8).tobytes() for _ in range(count)]


def truncations(data: bytes, rng: np.random.Generator, count: int) -> list[bytes]:
    return [data[:int(rng.integers(0, len(data)))] for _ in range(count)]


def bit_flips(data: bytes, rng: np.random.Generator, count: int, flips: int = 3) -> list[bytes]:
    mutated = []
    for _ in range(count):
        copy = bytearray(data)
        for position in rng.integers(0, len(copy), flips):
            copy[position] ^= 1 << int(rng.integers(0, 8))
        mutated.append(bytes(copy))
    return mutated


def tampered(message: Message, edit) -> bytes:
    """The message encoded, its msgpack envelope changed by edit(envelope), re-packed."""
    envelope = msgpack.unpackb(encode(message))
    edit(envelope)
    return msgpack.packb(envelope, use_bin_type=True)


def flood_episode(config: Config, index: int, steps: int = 6, shape=None, seed: int = 0) -> Episode:
    network = config.network
    shape = shape or (network.frame_height, network.frame_width, network.frame_channels)
    frames = np.random.default_rng(seed + index).integers(0, 40, (steps + 1, *shape), dtype=np.uint8)
    return Episode(observations=FrameStack.from_array(frames), actions=np.zeros(steps, np.int64),
                   rewards=np.full(steps, 0.5, np.float32), terminated=True, truncated=False, actor_id=FLOOD_ACTOR,
                   start_set="train", start_index=0, weights_version=np.full(steps, -1, np.int64), epsilon=1.0,
                   seed=0, episode_index=index, incarnation=0xF100D)


def examples(config: Config) -> dict[type, Message]:
    """A valid message of every type, sized for the run where it matters."""
    frames = FrameStack.from_array(np.zeros((2 * 3, 8, 8, 3), np.uint8))
    return {
        Episode: flood_episode(config, 0),
        TraceBatchRequest: TraceBatchRequest(request_id=9, batch_size=2, trace_length=config.learner.trace_length),
        TraceBatch: TraceBatch(request_id=9, observations=frames, actions=np.zeros((2, 2), np.int64),
                               rewards=np.zeros((2, 2), np.float32), terminated=np.zeros((2, 2), bool),
                               weights_version=np.zeros((2, 2), np.int64), env_steps_total=5, episodes_stored=1),
        Weights: Weights(version=3, tensors={"w": np.ones((2, 2), np.float32)}),
        ExplorationState: exploration_message(make_strategy(config.exploration, config.network.n_actions)),
        Stats: Stats(source="replay", time=1.0, values={"episodes": 3, "env_steps_total": 100}),
        LearnerStats: example_learner_stats(),
        ActorStats: example_actor_stats(),
        EpisodeRecord: EpisodeRecord(actor_id=FLOOD_ACTOR, episode_index=0, length=5, episode_return=1.0,
                                     collided=False, start_set="train", start_index=0, epsilon=1.0,
                                     weights_version=0, wall_time=1.0, time=1.0),
        RateState: example_rate(),
        ReplayStats: example_replay_stats(),
        EpisodeAck: EpisodeAck(actor_id=FLOOD_ACTOR, incarnation=0xF100D, received=np.zeros(0, np.int64),
                               kept=np.arange(3, dtype=np.int64), refused=np.zeros(0, np.int64)),
    }


def wrong_types(config: Config, right: type) -> list[bytes]:
    return [encode(message) for kind, message in examples(config).items() if kind is not right]


def misfit_episodes(config: Config) -> dict[str, bytes]:
    """Well-formed episodes that do not fit the run, by the replay's rejection kind."""
    network = config.network
    corrupt = flood_episode(config, 101)
    blobs = list(corrupt.observations.blobs)
    damaged = bytearray(blobs[2])
    damaged[len(damaged) // 2] ^= 0xFF  # the header still declares the right size
    blobs[2] = bytes(damaged)
    corrupt.observations = FrameStack(blobs, corrupt.observations.frame_shape)
    return {
        "frame_shape": encode(flood_episode(config, 102, shape=(network.frame_height // 2, network.frame_width, 3))),
        "frames_corrupt": encode(corrupt),
        "actions": encode(dataclasses.replace(flood_episode(config, 103), actions=np.full(6, network.n_actions))),
        "rewards": encode(dataclasses.replace(flood_episode(config, 104), rewards=np.full(6, 3e38, np.float32))),
        "length": encode(flood_episode(config, 105, steps=config.env.max_steps + 1)),
        "weights_version": encode(dataclasses.replace(flood_episode(config, 106),
                                                      weights_version=np.full(6, -50, np.int64))),
    }


def misfit_weights(config: Config) -> dict[str, bytes]:
    good = weights_to_numpy(D3RQN(config.network))
    other = weights_to_numpy(D3RQN(dataclasses.replace(config.network, lstm_units=config.network.lstm_units * 2)))
    name = next(iter(good))
    nan = np.full(good[name].size, np.nan, np.float32).tobytes()
    return {
        "another_network": encode(Weights(version=10**9, tensors=other)),
        "missing_tensor": encode(Weights(version=10**9, tensors=dict(list(good.items())[1:]))),
        "renamed": encode(Weights(version=10**9, tensors={f"x.{key}": value for key, value in good.items()})),
        "non_finite": tampered(Weights(version=10**9, tensors=good),
                               lambda e: e["fields"]["tensors"][name].__setitem__("data", nan)),
    }


def misfit_exploration(config: Config) -> dict[str, bytes]:
    state = examples(config)[ExplorationState]
    other = exploration_message(make_strategy(dataclasses.replace(config.exploration, strategy="softmax"),
                                              config.network.n_actions))
    bmc = exploration_message(make_strategy(dataclasses.replace(config.exploration, strategy="bmc"),
                                            config.network.n_actions))
    fields = lambda **values: lambda e: e["fields"].update(values)  # past the encoder, which refuses them all
    return {
        "unknown_strategy": tampered(state, fields(strategy="teleport")),
        "state_of_another": tampered(other, fields(strategy="vdbe")),  # softmax's params and state under vdbe
        "bad_params": tampered(state, fields(params={"alpha0": -5.0})),
        "bad_state": tampered(state, fields(state={"alpha": float("nan")})),
        "another_strategys_state": tampered(bmc, fields(state={"epsilon": 0.5})),
        "nan_state": tampered(bmc, lambda e: e["fields"]["state"].__setitem__("mean", float("nan"))),
        "negative_counts": tampered(bmc, lambda e: e["fields"]["counters"].__setitem__("updates", -1)),
        "params_not_a_map": tampered(state, fields(params=[1.0, 2.0])),
        "state_not_a_map": tampered(state, fields(state=[[1.0], []])),
        "another_strategy": encode(other),  # complete and valid: actors follow it until the learner's next state
    }


def misfit_replay_word() -> dict[str, bytes]:
    """The replay's rate and stats, well formed, whose counts no run of this budget can have, or whose fields
    break the rules the wire checks (re-packed past the encoder), or an older replay's untyped Stats."""
    absurd = example_rate(env_steps=10**15, start_env_steps=1e14)
    mark_past = lambda e: e["fields"].__setitem__("start_env_steps", 9e9)
    return {"absurd_rate": encode(absurd), "absurd_stats": encode(example_replay_stats(absurd)),
            "mark_past_steps": tampered(example_rate(), mark_past),
            "unknown_hold": tampered(example_rate(), lambda e: e["fields"].__setitem__("hold_reason", "forever")),
            "nested_mark_past_steps": tampered(example_replay_stats(),
                                               lambda e: mark_past({"fields": e["fields"]["rate"]})),
            "untyped_rate": encode(Stats(source="rate_limiter", time=1.0, values={"hold_reason": "", "env_steps": 1})),
            "untyped_stats": encode(Stats(source="replay", time=1.0, values={"env_steps_total": 100}))}


def misfit_stats() -> dict[str, bytes]:
    """Stats messages, with a replay's or a rate limiter's source, whose values are missing, mistyped or absurd;
    with a learner's or an actor's, an older sender's word that its typed message refuses on decode."""
    values = {
        "empty": {}, "text": {"env_steps_total": "many", "env_steps": "many", "hold_reason": 5, "updates": "x"},
        "nan": {"env_steps_total": float("nan"), "env_steps": float("inf"), "epsilon": float("nan")},
        "negative": {"env_steps_total": -7, "env_steps": -7, "start_env_steps": -3.0, "episodes": -1},
        "absurd": {"env_steps_total": 10**15, "env_steps": 10**15, "rate_start_env_steps": 1e300,
                   "start_env_steps": 1e300, "updates": 10**15},
        "mark_past_steps": {"env_steps_total": 50, "env_steps": 50, "start_env_steps": 90.0,
                            "rate_start_env_steps": 90.0},
        "unknown_hold": {"hold_reason": "forever", "env_steps": 1},
    }
    return {f"{source}_{name}": encode(Stats(source=source, time=1.0, values=value))
            for source in ("replay", "rate_limiter", "learner", "actor") for name, value in values.items()}
