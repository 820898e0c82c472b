"""The buffer's history rebuilt from a run's episodes in order (deploy/studies/buffer_history.py): by hand, and
against the real store's own counters over the same episodes."""

import dataclasses

import numpy as np
import pytest

from deploy.studies.buffer_history import history_lines, random_shares, rebuild
from replay.store import EpisodeStore
from tests.test_replay_store import make_episode


def test_an_episodes_random_share_is_its_steps_before_the_start():
    # steps 0-3, 4-7, 8-11 with the start at 6: all, half, none
    assert random_shares(np.array([4, 4, 4]), 6).tolist() == [1.0, 0.5, 0.0]


def test_the_history_by_hand():
    # ends 3, 6, 11, 16, 21; start 6; one update per step; capacity 2: full at 6 with the two random episodes.
    # Updates 1-5 (while episode 3 ran) draw from [random, random]; 6-10 from [random, learned]; 11-15 from
    # [learned, learned]: (5 x 1 + 5 x 0.5 + 5 x 0) / 15 = 0.5, all of them after the fill
    found = rebuild([3, 3, 5, 5, 5], capacity=2, trace_length=3, start_steps=6, steps_per_update=1.0)
    assert (found.stored, found.random_stored, found.full_at_env_steps, found.full_at_updates) == (5, 2.0, 6, 0)
    assert found.served_random_share == pytest.approx(0.5)
    assert found.served_random_share_after_full == pytest.approx(0.5)
    assert found.held_random_share_end == 0.0


def test_short_episodes_are_not_stored_and_a_buffer_that_never_fills_says_so():
    found = rebuild([2, 4, 4, 8], capacity=5, trace_length=3, start_steps=8, steps_per_update=2.0)
    # ends 2, 6, 10, 18: the first too short; the stored ones' shares 1, 0.5 (steps 6-9, start 8) and 0
    assert (found.stored, found.random_stored, found.full_at_env_steps) == (3, 1.5, None)
    assert found.served_random_share_after_full is None
    # 1 update while the third ran (held: one random episode), 4 while the fourth did (held 1 and 0.5)
    assert found.served_random_share == pytest.approx((1 + 4 * 0.75) / 5)
    assert found.held_random_share_end == pytest.approx(1.5 / 3)
    assert "| run | 5 | 3 (2) | never | 80.0% (–) | 50.0% |" in history_lines([("run", found)])


def test_the_rebuilt_share_matches_what_the_real_store_serves():
    rng = np.random.default_rng(5)
    lengths = np.concatenate([rng.integers(10, 40, 60), rng.integers(80, 200, 80)])
    start, per_update = int(lengths[:60].sum()), 4.0
    store = EpisodeStore(capacity=100, budget_bytes=1 << 32, trace_length=10, seed=3)
    begun, updates = 0, 0
    for length in lengths:
        end = begun + int(length)
        due = int(max(0, (end - start) / per_update))
        for _ in range(due - updates):
            store.sample(8)
        updates = due
        versions = np.where(np.arange(begun, end) < start, 0, 5)
        store.add(dataclasses.replace(make_episode(int(length)), weights_version=versions.astype(np.int64)))
        begun = end
    found = rebuild(lengths, 100, 10, start, per_update)
    fill = store.fill
    assert fill.full_at_env_steps == found.full_at_env_steps
    assert fill.sampled_random_steps / fill.sampled_steps == pytest.approx(found.served_random_share, abs=0.02)
    after = fill.sampled_random_steps_after_full / fill.sampled_steps_after_full
    assert after == pytest.approx(found.served_random_share_after_full, abs=0.02)
    assert found.held_random_share_end == pytest.approx(20 / 100)  # 60 random, 80 learned: the last 100 held
    # the store counts steps and the short random episodes hold fewer of them than their share of episodes
    assert 0 < fill.held_random_steps / (store.frames - len(store)) < found.held_random_share_end
