"""One valid instance of every wire message, and a field-by-field equality check (tests only)."""

from __future__ import annotations

import dataclasses

import numpy as np

from common.exploration.base import Counters
from common.exploration.bmc import BmcConfig, BmcPosterior
from common.wire.codecs import Message
from common.wire.frames import FrameStack
from common.wire.metrics import ActorStats, LearnerStats
from common.wire.messages import (BufferFillState, Episode, EpisodeAck, EpisodeRecord, ExplorationState,
                                  RateState, ReplayStats, Stats, TraceBatch, TraceBatchRequest, Weights, WeightsPiece,
                                  WeightsPieceAsk)

SMALL_FRAME = (6, 8, 3)


def random_frames(count: int, shape=SMALL_FRAME, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (count, *shape), dtype=np.uint8)


def example_episode(steps: int = 5, shape=SMALL_FRAME, seed: int = 0) -> Episode:
    rng = np.random.default_rng(seed)
    return Episode(
        observations=FrameStack.from_array(random_frames(steps + 1, shape, seed)),
        actions=rng.integers(0, 5, steps), rewards=rng.random(steps, dtype=np.float32),
        terminated=True, truncated=False, actor_id=3, start_set="train", start_index=7,
        weights_version=np.arange(steps, dtype=np.int64) + 40, epsilon=0.25, seed=-12, episode_index=9,
    )


def example_trace_batch(batch: int = 2, length: int = 3, shape=SMALL_FRAME, seed: int = 1) -> TraceBatch:
    rng = np.random.default_rng(seed)
    terminated = np.zeros((batch, length), dtype=bool)
    terminated[0, -1] = True
    return TraceBatch(
        request_id=5, observations=FrameStack.from_array(random_frames(batch * (length + 1), shape, seed)),
        actions=rng.integers(0, 5, (batch, length)), rewards=rng.random((batch, length), dtype=np.float32),
        terminated=terminated, weights_version=np.full((batch, length), 8, dtype=np.int64),
        env_steps_total=12_345, episodes_stored=17,
    )


def example_rate(**changes) -> RateState:
    """A rate limiter's word: updates started at 1,000 env steps, 48 of 50 due served, nobody held;
    `changes` replace fields (start_env_steps None and batches_served 0: before updates start)."""
    fields = dict(time=1.0, env_steps=1_200, batches_served=48, updates_due=50.0, start_env_steps=1_000.0,
                  hold_reason="", closed=False, refilling=False, refill_env_steps=0, lost_updates=0,
                  recounted_updates=0, error_buffer_updates=50.0, hold_updates=50.0, env_steps_per_update_target=4.0,
                  env_steps_per_update=4.17)
    return RateState(**{**fields, **changes})


def example_replay_stats(rate: RateState | None = None, **changes) -> ReplayStats:
    """A replay's stats around `rate` (example_rate()'s by default), its env steps those of the rate unless
    `changes` say otherwise."""
    rate = rate or example_rate()
    fields = dict(time=2.0, episodes=5, frames=1_205, bytes=4_000_000, env_steps_total=rate.env_steps,
                  inserted=5, evicted=0, evicted_for_budget=0, short_dropped=0, traces_served=480,
                  pending_requests=1, rejected_requests=0, expired_requests=0, failed_samples=0, episodes_missing=0,
                  episode_sources=1, restored_episodes=0, restore_skipped=0, late_episodes=0, late_env_steps=0,
                  snapshot_age_s=None, frame_bytes_mean=3_300.0, rate=rate, snapshot={"snapshots_written": 0},
                  rejected={"rejected_total": 0}, speeds={"inserted_per_s": 0.5},
                  fill=BufferFillState(held_random_steps=300, sampled_batches=48, sampled_steps=48 * 320,
                                       sampled_random_steps=4_000))
    return ReplayStats(**{**fields, **changes})


def example_learner_stats(**changes) -> LearnerStats:
    fields = dict(time=12.5, updates=3_000, env_steps=40_000, loss=0.012, epsilon=0.3, updates_per_s=4.6,
                  data_wait_share=0.25, weights_version=2_950, loss_abs_diff=float("nan"), grad_norm=1.5,
                  grad_norm_max=4.0, kappa=0.1, bmc_observations=12_000, precision="float32", update_path="fused",
                  sessions_reopened=1, hub_silent_s=0.5, env_steps_per_update=4.0, start_env_steps=28_000.0,
                  rejected={"rejected_total": 0, "malformed_stats": 2})
    return LearnerStats(**{**fields, **changes})


def example_actor_stats(**changes) -> ActorStats:
    fields = dict(time=12.5, episodes=40, episodes_sent=39, episodes_kept=38, episodes_in_flight=1,
                  weights_version=2_950, weights_behind=50, weights_behind_max=120, weights_download_s=0.25,
                  rejected={"rejected_weights_values": 1, "rejected_total": 1})
    return ActorStats(**{**fields, **changes})


def example_messages() -> list[Message]:
    rng = np.random.default_rng(2)
    return [
        example_episode(),
        TraceBatchRequest(request_id=5, batch_size=10, trace_length=10),
        example_trace_batch(),
        Weights(version=4, created=1_700_000_000.5, tensors={
            "conv.weight": rng.standard_normal((4, 3, 2, 2), dtype=np.float32),
            "scale": np.array(2.5),
            "steps": np.arange(3, dtype=np.int32),
            "mask": np.array([True, False]),
            "empty": np.zeros((0, 2), dtype=np.float32),
        }),
        example_exploration(),
        Stats(source="replay", time=12.5, values={"episodes": 3, "fill": 0.25, "state": "ok", "loss": float("nan")}),
        EpisodeRecord(actor_id=1, episode_index=2, length=300, episode_return=120.5, collided=False,
                      start_set="test", start_index=4, epsilon=0.05, weights_version=77, wall_time=12.0, time=99.0,
                      off_greedy=13),
        EpisodeAck(actor_id=2, incarnation=0x3FFF_FFFF_FFFF_FFFF, received=np.array([7, 8]),
                   kept=np.arange(5, dtype=np.int64), refused=np.zeros(0, np.int64)),
        example_rate(start_env_steps=None, batches_served=0, env_steps_per_update=None, hold_reason="budget"),
        example_replay_stats(snapshot_age_s=12.5),
        WeightsPieceAsk(version=-1, offset=49_152, size=49_152),
        WeightsPiece(version=12, total_bytes=100, offset=96, data=np.arange(4, dtype=np.uint8)),
        example_learner_stats(final=True),
        example_actor_stats(),
    ]


def example_exploration() -> ExplorationState:
    """A BMC learner's state some way into a run (its params not the defaults)."""
    return ExplorationState(strategy="bmc", params=(BmcConfig(alpha0=30.0, observations="per_transition"),),
                            epsilon=0.4, kappa=0.0, started=True,
                            counters=Counters(env_steps=12_000, updates=3_000, returns=12_000),
                            state=BmcPosterior(alpha=20.0, beta=30.0, count=12_000, mean=4.5, m2=900.0))


def assert_messages_equal(left: Message, right: Message) -> None:
    assert type(left) is type(right)
    for f in dataclasses.fields(left):
        _assert_values_equal(getattr(left, f.name), getattr(right, f.name), f.name)


def _assert_values_equal(left, right, where: str) -> None:
    if isinstance(left, FrameStack):
        assert isinstance(right, FrameStack) and left.frame_shape == right.frame_shape, where
        assert left.blobs == right.blobs, where
        np.testing.assert_array_equal(left.decode(), right.decode(), err_msg=where)
    elif isinstance(left, np.ndarray):
        assert isinstance(right, np.ndarray) and left.dtype == right.dtype and left.shape == right.shape, where
        np.testing.assert_array_equal(left, right, err_msg=where)
    elif isinstance(left, dict):
        assert isinstance(right, dict) and left.keys() == right.keys(), where
        for key in left:
            _assert_values_equal(left[key], right[key], f"{where}.{key}")
    elif isinstance(left, Message):
        assert_messages_equal(left, right)
    elif isinstance(left, float) and np.isnan(left):
        assert isinstance(right, float) and np.isnan(right), where
    else:
        assert type(left) is type(right) and left == right, where
