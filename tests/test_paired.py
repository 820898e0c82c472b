"""Paired comparisons across runs (common/analysis/paired.py): values computed by hand."""

import numpy as np
import pytest
from scipy import stats

from common.analysis.intervals import Bootstrap
from common.analysis.paired import paired_improvement, paired_improvement_estimate, signed_rank_p


def test_five_pairs_all_above_give_the_least_p_values():
    x, y = [0.9, 0.8, 0.7, 0.95, 0.6], [0.5, 0.4, 0.6, 0.5, 0.1]
    assert signed_rank_p(x, y, "greater") == pytest.approx(1 / 32)  # one sign pattern of 32: all positive
    assert signed_rank_p(x, y) == pytest.approx(2 / 32)
    assert signed_rank_p(y, x, "greater") == 1.0


def test_ties_and_zeros_by_hand():
    # differences +1, -1, +2, 0 (dropped): ranks by size 1.5, 1.5, 3; W+ = 1.5 + 3 = 4.5
    # the 8 sign patterns give W+ in {0, 1.5, 1.5, 3, 3, 4.5, 4.5, 6}: P(W+ >= 4.5) = 3/8, P(W+ <= 4.5) = 7/8
    x, y = [1.0, 0.0, 2.0, 5.0], [0.0, 1.0, 0.0, 5.0]
    assert signed_rank_p(x, y, "greater") == pytest.approx(3 / 8)
    assert signed_rank_p(x, y) == pytest.approx(6 / 8)
    assert signed_rank_p([1.0, 2.0], [1.0, 2.0]) == 1.0  # no difference at all


def test_it_agrees_with_scipy_where_scipy_is_exact():
    rng = np.random.default_rng(4)
    x, y = rng.random(12), rng.random(12)  # no ties, no zeros: scipy's exact distribution
    for alternative in ("greater", "two-sided"):
        expected = stats.wilcoxon(x, y, alternative=alternative, method="exact").pvalue
        assert signed_rank_p(x, y, alternative) == pytest.approx(expected)


def test_past_the_exact_range_the_normal_approximation_is_close():
    rng = np.random.default_rng(5)
    x, y = rng.random(30), rng.random(30) - 0.1
    expected = stats.wilcoxon(x, y, alternative="greater", method="exact").pvalue
    assert signed_rank_p(x, y, "greater") == pytest.approx(expected, abs=0.002)  # 0.0811 against 0.0821


def test_paired_improvement_by_hand():
    assert paired_improvement([1, 2, 3, 4], [0, 2, 5, 1]) == pytest.approx((1 + 0.5 + 0 + 1) / 4)
    with pytest.raises(ValueError, match="equal"):
        paired_improvement([1, 2], [1])


def test_the_interval_redraws_each_stratum_from_its_own_pairs():
    x, y = [1, 1, 1, 0, 0, 0], [0, 0, 0, 1, 1, 1]
    strata = ["a", "a", "a", "b", "b", "b"]  # a always wins, b always loses: every stratified draw gives 0.5
    estimate = paired_improvement_estimate(x, y, strata, Bootstrap(replicates=200))
    assert estimate.point == 0.5 and (estimate.interval.low, estimate.interval.high) == (0.5, 0.5)
    unstratified = paired_improvement_estimate(x, y, None, Bootstrap(replicates=200))
    assert unstratified.interval.low < 0.5 < unstratified.interval.high
    with pytest.raises(ValueError, match="one stratum a pair"):
        paired_improvement_estimate(x, y, ["a"], Bootstrap(replicates=10))
