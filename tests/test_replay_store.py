import dataclasses

import numpy as np
import pytest

from common.wire.envelope import decode, encode
from common.wire.frames import FrameStack
from common.wire.messages import Episode, TraceBatch
from replay.store import EpisodeStore, StoredEpisode

FRAME = (6, 8, 3)


def make_episode(steps: int, first_value: int = 0, terminated: bool = True) -> Episode:
    """Frame i of the episode is filled with first_value + i, so traces can be traced back."""
    values = (np.arange(steps + 1) + first_value) % 256
    frames = np.broadcast_to(values[:, None, None, None], (steps + 1, *FRAME)).astype(np.uint8)
    return Episode(
        observations=FrameStack.from_array(frames),
        actions=(np.arange(steps) % 5).astype(np.int64),
        rewards=(first_value + np.arange(steps)).astype(np.float32),
        terminated=terminated, truncated=not terminated, actor_id=0, start_set="train", start_index=0,
        weights_version=np.full(steps, 7, dtype=np.int64), epsilon=1.0, seed=0, episode_index=0)


def test_short_episodes_are_counted_not_stored_but_their_steps_count():
    store = EpisodeStore(capacity=10, budget_bytes=1 << 30, trace_length=10)
    assert store.add(make_episode(9)) is False
    assert store.add(make_episode(10)) is True
    assert (len(store), store.short_dropped, store.env_steps_total) == (1, 1, 19)


def test_capacity_evicts_oldest_first():
    store = EpisodeStore(capacity=3, budget_bytes=1 << 30, trace_length=2, seed=1)
    for index in range(5):
        store.add(make_episode(4, first_value=index * 10))
    assert (len(store), store.evicted, store.frames) == (3, 2, 15)
    batch = store.sample(200)
    first_frames = batch.observations_array()[:, 0, 0, 0, 0]
    assert set(first_frames.tolist()) <= set(range(20, 45))  # episodes 0 and 1 are gone


def test_byte_budget_evicts_but_keeps_the_newest():
    probe = make_episode(20)
    one = probe.observations.nbytes + probe.actions.nbytes + probe.rewards.nbytes + probe.weights_version.nbytes
    store = EpisodeStore(capacity=100, budget_bytes=int(2.5 * one), trace_length=5)
    for index in range(6):
        store.add(make_episode(20, first_value=index))
    assert len(store) == 2
    assert store.bytes <= 2.5 * one


def test_traces_are_consecutive_and_never_cross_an_episode_end():
    store = EpisodeStore(capacity=10, budget_bytes=1 << 30, trace_length=4, seed=3)
    store.add(make_episode(4, first_value=100))  # exactly one trace fits
    store.add(make_episode(30, first_value=0))
    batch = store.sample(300, request_id=9)
    observations = batch.observations_array()
    assert observations.shape == (300, 5, *FRAME)
    first = observations[:, :, 0, 0, 0].astype(int)
    assert (np.diff(first, axis=1) == 1).all()
    # the reward of step t is first_value + t, so it matches the trace's frame
    assert np.array_equal(batch.rewards, first[:, :-1].astype(np.float32))
    assert (batch.weights_version == 7).all() and batch.request_id == 9
    # terminated only on the last step of a trace that ends its (terminated) episode
    ends = first[:, -1] == np.where(first[:, 0] >= 100, 104, 30)
    assert np.array_equal(batch.terminated[:, -1], ends)
    assert not batch.terminated[:, :-1].any()
    assert ends.any() and (~ends).any()


def test_truncated_episode_end_is_not_terminal():
    store = EpisodeStore(capacity=10, budget_bytes=1 << 30, trace_length=4, seed=0)
    store.add(make_episode(4, terminated=False))
    assert not store.sample(10).terminated.any()


def test_episodes_and_starts_are_drawn_uniformly():
    store = EpisodeStore(capacity=10, budget_bytes=1 << 30, trace_length=2, seed=5)
    store.add(make_episode(3, first_value=0))  # 2 possible starts
    store.add(make_episode(50, first_value=100))  # 49 possible starts
    first = store.sample(20_000).observations_array()[:, 0, 0, 0, 0].astype(int)
    share_short = np.mean(first < 100)
    assert abs(share_short - 0.5) < 0.02  # episode first, uniformly, whatever its length
    counts = np.bincount(first[first < 100], minlength=2)
    assert abs(counts[0] / counts.sum() - 0.5) < 0.03


def test_sampled_traces_share_stored_frames():
    store = EpisodeStore(capacity=10, budget_bytes=1 << 30, trace_length=3, seed=0)
    episode = make_episode(3)
    store.add(episode)
    batch = store.sample(5)
    stored_ids = {id(blob) for blob in episode.observations.blobs}
    assert {id(blob) for blob in batch.observations.blobs} <= stored_ids


def test_sample_round_trips_the_wire():
    store = EpisodeStore(capacity=10, budget_bytes=1 << 30, trace_length=3, seed=0)
    store.add(make_episode(8))
    batch = store.sample(4)
    again = decode(encode(batch), TraceBatch)
    assert np.array_equal(again.observations_array(), batch.observations_array())
    assert again.env_steps_total == 8 and again.episodes_stored == 1


def test_empty_store_cannot_sample():
    with pytest.raises(LookupError):
        EpisodeStore(capacity=1, budget_bytes=1 << 20, trace_length=2).sample(1)


def test_a_stored_state_store_keeps_state_rows_and_hands_each_trace_the_row_of_its_first_step():
    episode = make_episode(12, first_value=0)
    rows = np.zeros((12, 2, 3), np.float16)
    rows[:, 0, 0] = np.arange(12)  # the row of step t holds t: a trace's first frame value names its row
    rows[:, 1, 2] = -np.arange(12)
    episode.recurrent_state = rows
    store = EpisodeStore(capacity=4, budget_bytes=1 << 30, trace_length=4, seed=5, state_units=3)
    store.add(episode)
    assert store.bytes == (episode.observations.nbytes + 12 * (8 + 4 + 8) + rows.nbytes)
    batch = store.sample(50)
    first = batch.observations_array()[:, 0, 0, 0, 0].astype(np.float16)
    assert batch.initial_state.shape == (50, 2, 3)
    np.testing.assert_array_equal(batch.initial_state[:, 0, 0], first)
    np.testing.assert_array_equal(batch.initial_state[:, 1, 2], -first)
    again = decode(encode(batch), TraceBatch)
    np.testing.assert_array_equal(again.initial_state, batch.initial_state)

    plain = EpisodeStore(capacity=4, budget_bytes=1 << 30, trace_length=4)  # the paper's: rows dropped
    plain.add(episode)
    assert plain.episodes()[0].states is None and plain.sample(3).initial_state.shape == (0, 2, 0)


def test_a_stored_state_store_serves_zero_rows_for_an_episode_kept_without_them():
    store = EpisodeStore(capacity=4, budget_bytes=1 << 30, trace_length=4, state_units=3)
    store.restore([dataclasses.replace(StoredEpisode.from_episode(make_episode(6)), seq=0)], {})
    batch = store.sample(2)
    assert batch.initial_state.shape == (2, 2, 3) and not batch.initial_state.any()


def test_by_steps_makes_every_trace_held_equally_likely():
    """Lengths 10 and 40 with traces of 10: 1 and 31 starts. An episode uniformly draws the short one half the
    time; by steps, 1 time in 32."""
    shares = {}
    for by_steps in (False, True):
        store = EpisodeStore(capacity=10, budget_bytes=1 << 30, trace_length=10, seed=6, by_steps=by_steps)
        store.add(make_episode(10, first_value=200))
        store.add(make_episode(40, first_value=0))
        first = store.sample(4000).observations_array()[:, 0, 0, 0, 0]
        shares[by_steps] = float(np.mean(first == 200))
    assert shares[False] == pytest.approx(1 / 2, abs=0.03)
    assert shares[True] == pytest.approx(1 / 32, abs=0.01)


def test_the_papers_sampling_is_unchanged_by_the_option_being_there():
    """Off, a batch draws exactly what the paper's rule draws from the same seed: an episode, then a start."""
    store = EpisodeStore(capacity=10, budget_bytes=1 << 30, trace_length=3, seed=11)
    for index in range(4):
        store.add(make_episode(5 + index, first_value=50 * index))
    batch = store.sample(16)
    rng = np.random.default_rng(11)
    picks = rng.integers(4, size=16)
    starts = [int(rng.integers(5 + pick - 3 + 1)) for pick in picks]
    assert batch.observations_array()[:, 0, 0, 0, 0].tolist() == [50 * p + s for p, s in zip(picks, starts)]


def test_the_replay_samples_by_steps_only_when_its_config_says_so():
    from common.config_values import load_config
    from replay.service import ReplayService

    assert not ReplayService(load_config("smoke")).store.by_steps
    assert ReplayService(load_config("smoke", overrides={"replay.sample_by_steps": True})).store.by_steps
