"""The bootstrap of the evaluation tables against cases worked out by hand or by enumeration."""

import collections
import itertools

import numpy as np
import pytest
from scipy.stats import trim_mean

from common.analysis.intervals import (Bootstrap, Cell, bootstrap_weights, cell_intervals, cell_statistics,
                                       percentile_interval, profile_band, weighted_iqm)

REPLICATES = 20_000


def cell(runs, starts, lengths, capped=None, returns=None, progress=None):
    n = len(lengths)
    return Cell.of(runs, starts, lengths, capped if capped is not None else [False] * n,
                   returns if returns is not None else [0.5 * length for length in lengths],
                   progress if progress is not None else [float(length) for length in lengths])


def replicate_frequencies(values):
    counts = collections.Counter(np.round(values, 9).tolist())
    return {value: count / len(values) for value, count in counts.items()}


def replicates_of(c, statistic, replicates=REPLICATES, seed=0):
    weights = bootstrap_weights(c.runs, c.starts, replicates, np.random.default_rng(seed))
    return cell_statistics(c, weights)[statistic]


# --- interquartile mean ---------------------------------------------------------------------------

@pytest.mark.parametrize("values, expected", [
    ([1, 2, 3, 4, 5, 6, 7, 8], 4.5),  # the middle four
    ([1, 2, 3, 100], 2.5),  # the outlier is cut
    ([0, 0, 0, 2000], 0.0),
    ([1, 2, 3, 4, 5], 3.0),  # 2 and 4 count three quarters each: (1.5 + 3 + 3) / 2.5
    ([7], 7.0),
    ([5, 5, 5], 5.0),
])
def test_iqm_of_known_arrays(values, expected):
    assert weighted_iqm(np.array(values, dtype=float), np.ones(len(values))) == pytest.approx(expected)


def test_iqm_is_scipys_trim_mean_for_multiples_of_four_and_counts_act_as_repeats():
    rng = np.random.default_rng(3)
    for size in (4, 8, 40, 300):
        values = rng.integers(1, 2000, size).astype(float)
        assert weighted_iqm(values, np.ones(size)) == pytest.approx(trim_mean(values, 0.25))
    values = np.array([4.0, 1.0, 3.0, 2.0])
    counts = np.array([1.0, 2.0, 1.0, 0.0])  # the sample 1, 1, 3, 4: its middle half is 1 and 3
    assert weighted_iqm(values, counts) == pytest.approx(2.0)
    rows = weighted_iqm(values, np.stack([counts, np.ones(4)]))
    assert rows == pytest.approx([2.0, 2.5])


# --- intervals ----------------------------------------------------------------------------------------

def test_degenerate_data_gives_zero_width_intervals_at_the_value():
    every_cap = cell(runs=[0, 0, 1, 1], starts=[0, 1, 0, 1], lengths=[2000] * 4, capped=[True] * 4,
                     returns=[1500.0] * 4, progress=[1980.0] * 4)
    intervals = cell_intervals(every_cap, Bootstrap(replicates=500))
    expected = {"mean_length": 2000, "iqm_length": 2000, "cfr": 1.0, "reward_per_step": 0.75, "progress_m": 1980}
    for name, value in expected.items():
        assert (intervals[name].low, intervals[name].high) == pytest.approx((value, value)), name
        assert intervals[name].width == 0


def test_reward_per_step_is_pooled_over_steps():
    # 0.5 per step in every episode: the pooled ratio is 0.5 whatever the lengths drawn
    c = cell(runs=[0, 0, 0], starts=[0, 0, 1], lengths=[1, 10, 100], returns=[0.5, 5.0, 50.0])
    point = cell_statistics(c, np.ones(3))
    assert point["reward_per_step"] == pytest.approx(0.5)
    assert point["mean_length"] == pytest.approx(37.0)
    interval = cell_intervals(c, Bootstrap(replicates=500))["reward_per_step"]
    assert (interval.low, interval.high) == pytest.approx((0.5, 0.5))
    # a 1-step episode worth 1 and a 3-step one worth 0: 1/4 per step, not the mean of 1 and 0
    assert cell_statistics(cell([0, 0], [0, 1], [1, 3], returns=[1.0, 0.0]), np.ones(2))["reward_per_step"] == 0.25


def test_two_trials_of_one_start_give_the_enumerated_distribution():
    # One run, one start, trials capped / not: a replicate draws 2 of 2, so the CFR is
    # 0, 1/2 or 1 with probabilities 1/4, 1/2, 1/4.
    c = cell(runs=[0, 0], starts=[0, 0], lengths=[2000, 10], capped=[True, False])
    frequencies = replicate_frequencies(replicates_of(c, "cfr"))
    assert sorted(frequencies) == [0.0, 0.5, 1.0]
    assert [frequencies[v] for v in (0.0, 0.5, 1.0)] == pytest.approx([0.25, 0.5, 0.25], abs=0.01)
    interval = cell_intervals(c, Bootstrap(replicates=REPLICATES))["cfr"]
    assert (interval.low, interval.high) == (0.0, 1.0)
    narrow = cell_intervals(c, Bootstrap(replicates=REPLICATES, confidence=0.4))["cfr"]  # the 30% and 70% points
    assert (narrow.low, narrow.high) == (0.5, 0.5)


def test_runs_are_resampled_whole_across_starts():
    # Run 0 reaches the cap from both starts, run 1 from neither. Drawing runs per start
    # (as rliable's stratified bootstrap does per task) would give CFRs of 1/4 and 3/4; drawing
    # whole runs gives only 0, 1/2 and 1.
    c = cell(runs=[0, 0, 1, 1], starts=[0, 1, 0, 1], lengths=[2000, 2000, 5, 5], capped=[True, True, False, False])
    frequencies = replicate_frequencies(replicates_of(c, "cfr"))
    assert sorted(frequencies) == [0.0, 0.5, 1.0]
    assert [frequencies[v] for v in (0.0, 0.5, 1.0)] == pytest.approx([0.25, 0.5, 0.25], abs=0.01)


def test_two_stage_distribution_matches_full_enumeration():
    # Two runs of two trials from one start: lengths 1, 3 (run A) and 5, 7 (run B). A replicate
    # draws two runs, then two trials of each drawn run: 2^2 * (2^2)^2 = 64 equally likely outcomes.
    lengths = {"A": [1, 3], "B": [5, 7]}
    exact = collections.Counter()
    for runs in itertools.product("AB", repeat=2):
        for trials in itertools.product((0, 1), repeat=4):
            drawn = [lengths[runs[0]][trials[0]], lengths[runs[0]][trials[1]],
                     lengths[runs[1]][trials[2]], lengths[runs[1]][trials[3]]]
            exact[sum(drawn) / 4] += 1 / 64
    c = cell(runs=["A", "A", "B", "B"], starts=[0] * 4, lengths=[1, 3, 5, 7])
    frequencies = replicate_frequencies(replicates_of(c, "mean_length", replicates=40_000))
    assert sorted(frequencies) == sorted(exact)
    for value, probability in exact.items():
        assert frequencies[value] == pytest.approx(probability, abs=0.006), value
    # The exact 2.5% point is 1.5 (P(1.0) = 1/64 < 0.025) and the 97.5% point 6.5.
    interval = cell_intervals(c, Bootstrap(replicates=40_000))["mean_length"]
    assert (interval.low, interval.high) == (1.5, 6.5)


def test_intervals_are_reproducible_from_the_seed_and_contain_the_estimate():
    rng = np.random.default_rng(0)
    lengths = rng.integers(5, 2000, 60)
    c = cell(runs=np.repeat([0, 1, 2], 20), starts=np.tile(np.repeat(np.arange(10), 2), 3), lengths=lengths,
             capped=lengths > 1500)
    first, again = cell_intervals(c, Bootstrap(300, seed=4)), cell_intervals(c, Bootstrap(300, seed=4))
    assert first == again
    point = cell_statistics(c, np.ones(len(lengths)))
    for name in ("mean_length", "iqm_length", "cfr"):
        assert first[name].low < point[name] < first[name].high


def test_missing_progress_gives_no_interval():
    c = cell(runs=[0, 0], starts=[0, 1], lengths=[3, 4], progress=[float("nan")] * 2)
    interval = cell_intervals(c, Bootstrap(replicates=50))["progress_m"]
    assert np.isnan(interval.low) and np.isnan(interval.high)
    assert np.isnan(percentile_interval(np.array([]), 0.95).low)


def test_bad_cells_and_settings_are_refused():
    with pytest.raises(ValueError, match="same positive number"):
        cell(runs=[0], starts=[0, 1], lengths=[1, 2])
    with pytest.raises(ValueError, match="at least one step"):
        cell(runs=[0], starts=[0], lengths=[0])
    with pytest.raises(ValueError, match="confidence"):
        Bootstrap(confidence=1.0)


# --- performance profile ------------------------------------------------------------------------------------

def test_profile_band_is_the_share_longer_than_each_threshold():
    lengths = np.array([10.0, 20.0, 30.0, 2000.0])
    thresholds = np.array([0.0, 10.0, 25.0, 1999.0, 2000.0])
    weights = bootstrap_weights(np.zeros(4), np.zeros(4), 2000, np.random.default_rng(0))
    observed, low, high = profile_band(lengths, weights, thresholds, 0.95)
    assert observed.tolist() == [1.0, 0.75, 0.5, 0.25, 0.0]
    assert low[0] == high[0] == 1.0 and low[-1] == high[-1] == 0.0  # every draw agrees there
    assert (low <= observed).all() and (observed <= high).all() and (low[1:4] < high[1:4]).all()
