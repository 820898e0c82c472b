"""Statistics across seeds: the IQM, the probability of improvement, the stratified bootstrap and the claims
rule, against values worked by hand."""

from __future__ import annotations

import numpy as np
import pytest

from common.analysis.across_seeds import (CANT_TELL, LEAN, SUPPORTED, Estimate, claim, improvement_estimate, iqm,
                                          reverse_claim,
                                          iqm_estimate, mann_whitney_p, pooled, probability_of_improvement, reading,
                                          score_matrix, seeds_to_support, smallest_p_value, stratified_replicates)
from common.analysis.intervals import Bootstrap, Interval


def test_iqm_is_the_mean_of_the_middle_half_of_all_scores_pooled():
    # sorted: -50 1 2 3 4 5 20 100; two cut from each end leave 2 3 4 5
    assert iqm([[1, 2, 3, 100], [4, 5, 20, -50]]) == pytest.approx(3.5)


def test_iqm_cuts_whole_scores_when_their_count_is_not_a_multiple_of_four():
    # 6 scores: int(1.5) = 1 cut from each end, leaving 2 3 4 10 (a boundary counted in part would give 13/3)
    assert iqm([[1, 2], [3, 4], [10, 30]]) == pytest.approx(4.75)


def test_one_scalar_per_run_is_one_task():
    assert score_matrix([1.0, 2.0, 3.0]).shape == (3, 1)
    assert iqm([7.0, 1.0, 3.0, 5.0]) == pytest.approx(4.0)  # 1 3 5 7: the middle two


def test_probability_of_improvement_counts_ties_as_half_and_averages_tasks():
    x = [[1, 5], [3, 5]]
    y = [[2, 5], [3, 0]]
    # task 0: X {1, 3} against Y {2, 3}: only 3 > 2 wins, 3 = 3 is a half: 1.5 / 4
    # task 1: X {5, 5} against Y {5, 0}: each 5 ties one and beats one: 3 / 4
    assert probability_of_improvement(x, y) == pytest.approx((0.375 + 0.75) / 2)
    assert probability_of_improvement(y, x) == pytest.approx(1 - (0.375 + 0.75) / 2)


def test_probability_of_improvement_takes_runs_of_different_counts():
    # 1 < 2, 2 = 2, 3 > 2: (0 + 0.5 + 1) / 3
    assert probability_of_improvement([1, 2, 3], [2]) == pytest.approx(0.5)


def test_groups_must_share_their_tasks():
    with pytest.raises(ValueError, match="tasks"):
        probability_of_improvement(np.zeros((3, 10)), np.zeros((3, 9)))
    with pytest.raises(ValueError, match="finite"):
        iqm([1.0, float("nan")])


def test_pooled_stacks_the_runs_of_several_strategies():
    together = pooled([np.ones((3, 10)), np.zeros((3, 10)), [[2.0] * 10]])
    assert together.shape == (7, 10)
    assert together[:, 0].tolist() == [1, 1, 1, 0, 0, 0, 2]
    with pytest.raises(ValueError):
        pooled([np.ones((3, 10)), np.ones((3, 9))])


def test_stratified_replicates_are_shaped_and_drawn_from_the_seed():
    scores = np.arange(12.0).reshape(3, 4)
    drawn = stratified_replicates(scores, 50, np.random.default_rng(7))
    assert drawn.shape == (50, 3, 4)
    assert np.array_equal(drawn, stratified_replicates(scores, 50, np.random.default_rng(7)))
    assert not np.array_equal(drawn, stratified_replicates(scores, 50, np.random.default_rng(8)))


def test_stratified_replicates_redraw_runs_within_each_task_independently():
    # task t holds 100 t + run: a drawn score names its task and its run
    runs, tasks = 3, 5
    scores = 100.0 * np.arange(tasks)[None, :] + np.arange(runs)[:, None]
    drawn = stratified_replicates(scores, 400, np.random.default_rng(0))
    task_of, run_of = drawn // 100, drawn % 100
    assert np.array_equal(task_of, np.broadcast_to(np.arange(tasks), drawn.shape))  # never from another task
    assert set(np.unique(run_of)) == {0, 1, 2}
    # redrawn per task, not a whole run at a time: some replicate row mixes runs across tasks
    assert (run_of.min(axis=2) != run_of.max(axis=2)).any()


def test_two_runs_give_the_enumerated_iqm_interval():
    # one task, runs 0 and 4: a redraw is {0, 0}, {0, 4} or {4, 4}, IQM 0, 2 or 4 (1/4, 1/2, 1/4)
    estimate = iqm_estimate([0.0, 4.0], Bootstrap(replicates=4000, seed=3))
    assert estimate == Estimate(2.0, Interval(0.0, 4.0))
    narrow = iqm_estimate([0.0, 4.0], Bootstrap(replicates=4000, confidence=0.4, seed=3))
    assert narrow.interval == Interval(2.0, 2.0)  # the middle 40% of the replicates are all 2


def test_improvement_interval_is_reproducible_and_exact_when_the_groups_lie_apart():
    ahead, behind = np.full((3, 10), 9.0) + np.arange(3)[:, None], np.zeros((4, 10))
    assert improvement_estimate(ahead, behind) == Estimate(1.0, Interval(1.0, 1.0))
    x, y = np.random.default_rng(1).normal(size=(3, 10)), np.random.default_rng(2).normal(size=(3, 10))
    bootstrap = Bootstrap(replicates=300, seed=5)
    first = improvement_estimate(x, y, bootstrap)
    assert first == improvement_estimate(x, y, bootstrap)
    assert first.interval.low < first.point < first.interval.high


def test_smallest_p_values_of_exact_one_sided_tests():
    assert smallest_p_value(3, 3) == pytest.approx(0.05)  # 1 / C(6, 3) = 1 / 20
    assert smallest_p_value(4, 4) == pytest.approx(1 / 70)
    assert smallest_p_value(12, 6) == pytest.approx(1 / 18564)
    with pytest.raises(ValueError):
        smallest_p_value(0, 3)


def test_three_seeds_a_side_can_never_support_a_pairwise_claim_and_four_can():
    assert seeds_to_support() == 4
    assert seeds_to_support(0.01) == 5  # 1/70 is not below 0.01; 1/252 is


def test_the_test_reaches_its_smallest_p_value_when_the_groups_lie_apart():
    assert mann_whitney_p([5, 6, 7], [1, 2, 3]) == pytest.approx(smallest_p_value(3, 3))
    assert mann_whitney_p(np.arange(12.0) + 10, np.arange(6.0)) == pytest.approx(smallest_p_value(12, 6))


def test_the_exact_p_value_without_ties_by_hand():
    # A {3, 5, 6} against B {1, 2, 4}: U = 8 of 9; of the 20 splits of 1..6 only A = {4, 5, 6} (U = 9) and this
    # one reach 8
    assert mann_whitney_p([3, 5, 6], [1, 2, 4]) == pytest.approx(2 / 20)


def test_the_exact_p_value_with_ties_by_hand():
    # A {1, 0} against B {0, 0}: U = 2 + 2 halves = 3. Of the 6 splits of {0, 0', 0'', 1}, the 3 that give A the 1
    # reach U = 3 (the others give 1): p = 1/2. scipy's exact U distribution, which ignores ties, says 1/3.
    assert mann_whitney_p([1, 0], [0, 0]) == pytest.approx(1 / 2)


def test_the_exact_p_value_of_one_run_against_two_with_a_tie_by_hand():
    # A grid with one seed done: A {93} against B {87, 93}. U = 1 + 1/2 = 1.5. Of the 3 splits, A = either 93
    # reaches 1.5 and A = 87 gives 0: p = 2/3. (scipy's permutation method refuses a side of one run.)
    assert mann_whitney_p([93], [87, 93]) == pytest.approx(2 / 3)
    assert mann_whitney_p([2], [1]) == pytest.approx(1 / 2)


def test_the_test_scores_a_run_by_its_mean_over_the_tasks():
    a, b = [[0, 10], [6, 6], [4, 12]], [[1, 1], [2, 4], [3, 3]]
    assert mann_whitney_p(a, b) == pytest.approx(mann_whitney_p([5, 6, 8], [1, 3, 3]))


@pytest.mark.parametrize("p_value, improvement, expected", [
    (0.01, Estimate(0.9, Interval(0.6, 1.0)), SUPPORTED),
    (0.05, Estimate(0.9, Interval(0.6, 1.0)), LEAN),  # p must lie below 0.05
    (0.01, Estimate(0.8, Interval(0.5, 1.0)), LEAN),  # the interval must lie wholly above 0.5
    (0.30, Estimate(0.6, Interval(0.3, 0.9)), LEAN),
    (0.50, Estimate(0.5, Interval(0.2, 0.8)), CANT_TELL),
    (0.90, Estimate(0.2, Interval(0.0, 0.4)), CANT_TELL),
])
def test_the_reading_of_clear_cut_inputs(p_value, improvement, expected):
    assert reading(p_value, improvement) == expected


def test_a_claim_of_twelve_runs_against_six_apart_is_supported_and_three_against_three_only_leans():
    tasks = 10
    ahead = pooled([np.full((3, tasks), 1000.0 + 10 * strategy) + np.arange(3)[:, None] for strategy in range(4)])
    behind = pooled([np.full((3, tasks), 100.0 + 10 * strategy) + np.arange(3)[:, None] for strategy in range(2)])
    found = claim(ahead, behind, Bootstrap(replicates=200))
    assert (found.a_runs, found.b_runs, found.reading) == (12, 6, SUPPORTED)
    assert found.p_value == pytest.approx(1 / 18564)
    assert claim(ahead[:3], behind[:3], Bootstrap(replicates=200)).reading == LEAN  # p = 0.05 at best
    assert claim(behind, ahead, Bootstrap(replicates=200)).reading == CANT_TELL


def test_a_claim_read_the_other_way_round_doubles_its_p_value():
    ahead, behind = [[1.0]] * 4, [[0.0]] * 3
    found = reverse_claim(behind, ahead, Bootstrap(replicates=200))
    # 4 runs all above 3: one-sided 1/C(7, 3) = 1/35, doubled 2/35 = 0.057, not below 0.05: a lean
    assert (found.a_runs, found.b_runs) == (4, 3) and found.p_value == pytest.approx(2 / 35)
    assert found.improvement.point == 1.0 and found.reading == LEAN
    found = reverse_claim([[0.0]] * 4, [[1.0]] * 4, Bootstrap(replicates=200))
    assert found.p_value == pytest.approx(2 / 70) and found.reading == SUPPORTED  # 1/C(8, 4), doubled
    assert reverse_claim([[1.0]] * 3, [[0.0]] * 3).p_value == 1.0  # twice a p-value near 1 stays 1
