"""The buffer's fill and the random phase's share of what it holds and serves (replay/buffer_fill.py)."""

import dataclasses

import msgpack
import numpy as np

from common.config_values import load_config
from common.wire.envelope import decode, encode
from common.wire.messages import BufferFillState, ReplayStats, flat_values
from deploy.launcher.stack_monitor import StackMonitor
from replay.buffer_fill import random_steps
from replay.store import EpisodeStore
from tests.test_replay_store import make_episode
from tests.wire_examples import example_replay_stats


def episode_acted_with(steps: int, versions) -> object:
    return dataclasses.replace(make_episode(steps), weights_version=np.asarray(versions, dtype=np.int64))


def test_a_step_is_of_the_random_phase_when_acted_without_trained_weights():
    assert random_steps(np.array([-1, 0, 1, 5, 0])) == 3
    assert random_steps(np.array([[1, 2], [3, 4]])) == 0


def test_held_random_steps_follow_insertions_and_evictions():
    store = EpisodeStore(capacity=2, budget_bytes=1 << 30, trace_length=2)
    store.add(episode_acted_with(4, [-1, 0, 0, 0]))  # 4 random
    store.add(episode_acted_with(4, [0, 0, 3, 3]))  # 2 random
    assert store.fill.held_random_steps == 6
    store.add(episode_acted_with(4, [5, 5, 5, 5]))  # evicts the first
    assert store.fill.held_random_steps == 2


def test_the_first_fill_is_marked_once_with_its_env_steps_and_batches():
    store = EpisodeStore(capacity=3, budget_bytes=1 << 30, trace_length=2, seed=1)
    store.add(episode_acted_with(4, [0] * 4))
    store.add(episode_acted_with(5, [0] * 5))
    store.sample(2)
    store.sample(2)
    assert store.fill.full_at_env_steps == 0
    store.add(episode_acted_with(6, [0] * 6))
    assert (store.fill.full_at_env_steps, store.fill.full_at_batches) == (15, 2)
    store.add(episode_acted_with(3, [0] * 3))
    assert (store.fill.full_at_env_steps, store.fill.full_at_batches) == (15, 2)


def test_samples_count_their_random_steps_before_and_after_the_fill():
    store = EpisodeStore(capacity=2, budget_bytes=1 << 30, trace_length=3, seed=4)
    store.add(episode_acted_with(6, [-1, 0, 0, 1, 2, 3]))
    before = store.sample(5)
    store.add(episode_acted_with(6, [4] * 6))  # full from here
    after = [store.sample(7) for _ in range(3)]
    fill = store.fill
    expected_before = random_steps(before.weights_version)
    expected_after = sum(random_steps(batch.weights_version) for batch in after)
    assert (fill.sampled_batches, fill.sampled_steps) == (4, 5 * 3 + 3 * 7 * 3)
    assert fill.sampled_random_steps == expected_before + expected_after
    assert (fill.sampled_steps_after_full, fill.sampled_random_steps_after_full) == (3 * 7 * 3, expected_after)
    assert 0 < expected_before < 15


def test_a_snapshot_round_trip_keeps_the_counters_and_recounts_what_is_held():
    store = EpisodeStore(capacity=2, budget_bytes=1 << 30, trace_length=2, seed=2)
    for versions in ([0, 0, 0], [0, 7, 7], [7, 7, 7]):
        store.add(episode_acted_with(3, versions))
        store.sample(3)
    again = EpisodeStore(capacity=2, budget_bytes=1 << 30, trace_length=2)
    again.restore(store.episodes(), store.counters())
    assert dataclasses.asdict(again.fill.state()) == dataclasses.asdict(store.fill.state())
    assert again.fill.held_random_steps == 1


def test_a_snapshot_from_before_these_counters_restores_them_at_zero():
    store = EpisodeStore(capacity=2, budget_bytes=1 << 30, trace_length=2)
    store.restore([], {"inserted": 4, "evicted": 2, "sampled_steps": "many"})
    assert dataclasses.asdict(store.fill.state()) == dataclasses.asdict(BufferFillState())
    assert store.inserted == 4


def test_replay_stats_carry_the_fill_and_old_stats_without_it_still_decode():
    stats = example_replay_stats()
    assert dataclasses.asdict(decode(encode(stats)).fill) == dataclasses.asdict(stats.fill)
    flat = flat_values(stats)
    assert (flat["fill_held_random_steps"], flat["fill_sampled_random_steps"]) == (300, 4_000)
    envelope = msgpack.unpackb(encode(stats), raw=False)
    del envelope["fields"]["fill"]  # what a replay that predates the field sends
    old = decode(msgpack.packb(envelope, use_bin_type=True), ReplayStats)
    assert dataclasses.asdict(old.fill) == dataclasses.asdict(BufferFillState())


def test_the_run_summary_says_the_buffer_and_its_fill():
    monitor = StackMonitor()
    config = load_config("smoke")
    assert monitor.summary(config)["replay_fill"] is None  # no stats from the replay yet
    monitor.on_replay_stats(example_replay_stats(), "d3rqn/r/replay/stats")
    summary = monitor.summary(config)
    assert summary["replay_capacity"] == config.replay.capacity
    assert (summary["replay_fill"]["held_random_steps"], summary["replay_fill"]["full_at_env_steps"]) == (300, 0)
