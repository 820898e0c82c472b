"""The comparison's differences: intervals hand-worked from small cells, the pairs compared, the report's table."""

from __future__ import annotations

import numpy as np
import pytest

from common.analysis.intervals import Bootstrap
from common.analysis.stats import EvaluationEpisode, episode_cell, summarise
from deploy.studies.comparison import ComparisonRow
from deploy.studies.differences import (chance_apart, chances_apart, compared_pairs, differences, differences_markdown, lie_apart,
                                observed_statistics)


def episode(length: int, start_set: str = "train", start_index: int = 0, trial: int = 0) -> EvaluationEpisode:
    return EvaluationEpisode(policy="greedy", start_set=start_set, start_index=start_index, trial=trial, seed=0,
                             length=length, end="collision", episode_return=0.5 * length, reward_bin_counts=(length,),
                             actions_digest=str(length), progress_m=float(length), streets=length // 4,
                             junctions=length // 8)


def row(strategy: str, lengths_by_run: list[list[int]], capacity: int = 1000, start_set: str = "train"
        ) -> ComparisonRow:
    episodes = [episode(length, start_set, trial=trial) for lengths in lengths_by_run
                for trial, length in enumerate(lengths)]
    runs = [run for run, lengths in enumerate(lengths_by_run) for _ in lengths]
    return ComparisonRow(strategy, capacity, len(lengths_by_run), summarise(episodes, runs), None,
                         tuple(range(len(lengths_by_run))), (100,) * len(lengths_by_run), episode_cell(episodes, runs))


def difference_of(found, statistic="mean_length"):
    (only,) = [d for d in found if d.statistic == statistic]
    return only


def test_a_constant_gap_is_exact_and_supported():
    found = differences([row("constant", [[10, 10, 10]]), row("bmc", [[4, 4, 4]])], Bootstrap(replicates=500))
    mean = difference_of(found)
    assert mean.observed == pytest.approx(6.0)
    assert (mean.interval.low, mean.interval.high) == pytest.approx((6.0, 6.0))
    assert mean.supported


def test_two_trials_against_a_constant_give_the_hand_worked_interval():
    # one run, one start, lengths 2 and 4: a redraw's mean is 2, 3 or 4 with chance 1/4, 1/2, 1/4, so the
    # difference from a constant 1 is 1, 2 or 3 and the central 95% of 4,000 redraws runs from 1 to 3
    mean = difference_of(differences([row("constant", [[2, 4]]), row("bmc", [[1, 1]])], Bootstrap(replicates=4000)))
    assert mean.observed == pytest.approx(2.0)
    assert (mean.interval.low, mean.interval.high) == (1.0, 3.0)
    assert mean.supported


def test_a_row_against_its_own_copy_is_not_supported_and_not_degenerate():
    # drawn independently, two copies of the same episodes differ by chance only: interval around 0, not a point
    lengths = [[5, 30, 80, 120], [10, 60, 90, 200]]
    mean = difference_of(differences([row("constant", lengths), row("bmc", lengths)], Bootstrap(replicates=1000)))
    assert mean.observed == 0.0
    assert mean.interval.low < 0.0 < mean.interval.high
    assert not mean.supported


def test_seeds_that_disagree_widen_the_interval_past_what_the_trials_alone_give():
    # pooled over two runs far apart, the run stage adds the spread between them
    tight = difference_of(differences([row("constant", [[50, 52], [50, 52]]), row("bmc", [[40, 42], [40, 42]])]))
    split = difference_of(differences([row("constant", [[20, 22], [80, 82]]), row("bmc", [[40, 42], [40, 42]])]))
    assert tight.observed == split.observed == pytest.approx(10.0)
    assert split.interval.width > 10 * tight.interval.width
    assert tight.supported and not split.supported


def test_pairs_are_strategies_within_a_capacity_then_capacities_within_a_strategy():
    rows = [row("constant", [[10]]), row("bmc", [[12]]), row("random", [[3]]),
            row("constant", [[11]], capacity=2000), row("bmc", [[9]], capacity=2000),
            row("constant", [[20]], start_set="test")]
    named = [((a.strategy, a.capacity, a.start_set), (b.strategy, b.capacity, b.start_set))
             for a, b in compared_pairs(rows)]
    assert named == [(("constant", 1000, "train"), ("bmc", 1000, "train")),
                     (("constant", 2000, "train"), ("bmc", 2000, "train")),
                     (("constant", 1000, "train"), ("constant", 2000, "train")),
                     (("bmc", 1000, "train"), ("bmc", 2000, "train"))]  # the random baseline is not compared


def test_observed_statistics_are_the_unweighted_ones():
    stats = observed_statistics(row("constant", [[2, 4, 6, 8]]))
    assert stats["mean_length"] == pytest.approx(5.0)
    assert stats["iqm_length"] == pytest.approx(5.0)  # middle half: 4 and 6
    assert stats["reward_per_step"] == pytest.approx(0.5)


def test_the_markdown_names_each_pair_and_says_when_only_the_trials_support_it():
    found = differences([row("constant", [[10, 10]]), row("bmc", [[4, 4]])], Bootstrap(replicates=200))
    text = differences_markdown(found)
    assert "### Differences, train set" in text
    line = next(line for line in text.splitlines() if line.startswith("| Constant"))
    assert "1 vs 1" in line and "+6.00 [+6.00, +6.00]" in line and line.endswith("| mean and IQM (trials only) | – |")


def test_the_same_rows_give_the_same_intervals():
    rows = [row("constant", [[5, 9, 13], [7, 8, 30]]), row("bmc", [[6, 6, 20], [1, 40, 9]])]
    first, second = differences(rows, Bootstrap(replicates=300)), differences(rows, Bootstrap(replicates=300))
    assert [(d.interval.low, d.interval.high) for d in first] == [(d.interval.low, d.interval.high) for d in second]
    assert np.isfinite([d.interval.low for d in first if d.statistic != "progress_m"]).all()


def test_a_rows_interval_does_not_move_when_other_rows_join_the_report():
    constant, bmc = row("constant", [[5, 9, 13], [7, 8, 30]]), row("bmc", [[6, 6, 20], [1, 40, 9]])
    alone = difference_of(differences([constant, bmc], Bootstrap(replicates=300)))
    joined = differences([row("random", [[1]]), row("softmax", [[3, 4]]), constant, bmc], Bootstrap(replicates=300))
    (same,) = [d for d in joined if d.statistic == "mean_length" and (d.first.strategy, d.second.strategy)
               == ("constant", "bmc")]
    assert (same.interval.low, same.interval.high) == (alone.interval.low, alone.interval.high)


def test_runs_lie_apart_only_when_every_run_of_one_side_is_beyond_every_run_of_the_other():
    # run means 10 and 20 against 15 and 16: pooled +4.5 apart from nothing, but the runs interleave
    interleaved = difference_of(differences([row("constant", [[10, 10], [20, 20]]), row("bmc", [[15, 15], [16, 16]])],
                                            Bootstrap(replicates=200)))
    assert interleaved.observed == pytest.approx(-0.5) and interleaved.runs_apart is False
    # run means 30 and 40 against 10 and 12: apart, and so is the reverse order of the pair
    apart = [row("constant", [[30, 30], [40, 40]]), row("bmc", [[10, 10], [12, 12]])]
    assert difference_of(differences(apart, Bootstrap(replicates=200))).runs_apart is True
    assert difference_of(differences(apart[::-1], Bootstrap(replicates=200))).runs_apart is True
    # one run a side: not asked
    assert difference_of(differences([row("constant", [[30]]), row("bmc", [[10]])])).runs_apart is None


def test_runs_with_a_missing_statistic_are_not_placed_apart_or_together():
    assert lie_apart(np.array([30.0, np.nan]), np.array([10.0, 12.0])) is None
    assert lie_apart(np.array([30.0, 40.0]), np.array([np.nan, 12.0])) is None
    assert lie_apart(np.array([30.0, 40.0]), np.array([10.0, 12.0])) is True


def test_the_chance_of_runs_lying_apart_counts_orderings():
    # two a side: of the 6 orderings of 4 values, aabb and bbaa; two against three: 2 of 10; three a side: 2 of 20
    assert chance_apart(2, 2) == pytest.approx(1 / 3)
    assert chance_apart(2, 3) == chance_apart(3, 2) == pytest.approx(1 / 5)
    assert chance_apart(3, 3) == pytest.approx(1 / 10)
    found = differences([row("constant", [[30, 30], [40, 40]]), row("bmc", [[10, 10], [12, 12], [14, 14]]),
                         row("softmax", [[5, 6], [7, 8]])], Bootstrap(replicates=50))
    assert chances_apart(found) == "2 against 2 one time in 3; 2 against 3 one time in 5"


def test_runs_apart_uses_each_runs_own_statistic():
    # IQM per run: run [1, 5, 5, 9] has middle half 5, 5; the pooled IQM would mix the runs' episodes
    rows = [row("constant", [[1, 5, 5, 9], [2, 6, 6, 40]]), row("bmc", [[3, 3, 3, 3], [4, 4, 4, 4]])]
    iqm = difference_of(differences(rows, Bootstrap(replicates=200)), "iqm_length")
    assert iqm.runs_apart is True  # 5 and 6 against 3 and 4
    mean = difference_of(differences(rows, Bootstrap(replicates=200)))
    assert mean.runs_apart is True  # 5 and 13.5 against 3 and 4


def test_the_markdown_says_whether_the_runs_lie_apart():
    found = differences([row("constant", [[30, 30], [40, 40]]), row("bmc", [[10, 10], [35, 35]])],
                        Bootstrap(replicates=200))
    line = next(line for line in differences_markdown(found).splitlines() if line.startswith("| Constant"))
    assert "2 vs 2" in line and line.endswith("| no |")
    single = differences_markdown(differences([row("constant", [[10, 10]]), row("bmc", [[4, 4]])]))
    assert next(line for line in single.splitlines() if line.startswith("| Constant")).endswith("| – |")
