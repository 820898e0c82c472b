"""Where the grid's runs failed (deploy/studies/grid_failures.py): the places their failures hit, and the prediction
read on the seed-2 runs, against outcomes worked by hand."""

import dataclasses
from collections import Counter
from types import SimpleNamespace

import numpy as np
import pytest

from deploy.studies import grid_failures
from deploy.studies.grid_failures import CONFIRMED, IN_THE_MEAN, PENDING, REFUTED, prediction_reading
from tests.grid_runs import episode


def grid_run(strategy: str, hard: float, seed: int = 2, cell=(1000, "paper")):
    """A run whose chosen policy reads `hard` from test starts 1, 2 and 9 and 100% from the others."""
    start_cfr = np.ones(10)
    start_cfr[[1, 2, 9]] = hard
    return SimpleNamespace(cell=cell, run=SimpleNamespace(strategy=strategy, seed=seed), start_cfr=start_cfr)


def scores(family, uniform):
    return dict(zip(grid_failures.SOFTMAX_FAMILY + grid_failures.UNIFORM, family + uniform))


def test_a_runs_score_is_its_mean_cfr_over_the_three_hard_starts():
    start_cfr = np.array([1.0, 0.0, 0.1, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.2])
    assert grid_failures.hard_start_score(start_cfr) == pytest.approx(0.1)


def test_only_the_seed_2_runs_of_the_paper_cell_are_read():
    runs = [grid_run("softmax", 0.2), grid_run("softmax", 0.9, seed=1), grid_run("vdbe", 0.5, cell=(2000, "paper")),
            grid_run("constant", 1.0)]
    read = grid_failures.prediction_scores(runs)
    assert read["softmax"] == pytest.approx(0.2) and read["constant"] == pytest.approx(1.0)
    assert read["vdbe"] is None and read["max_boltzmann"] is None
    assert prediction_reading(read) == (PENDING, None)


def test_every_softmax_family_run_below_every_other_confirms_it_at_p_005():
    reading, p_value = prediction_reading(scores([0.1, 0.2, 0.3], [0.9, 1.0, 0.8]))
    assert reading == CONFIRMED and p_value == pytest.approx(0.05)


def test_overlapping_runs_with_the_means_ordered_hold_in_the_mean():
    # pooled ranks .1:1 .2:2 .8:3 .9:4 .95:5 1.0:6; the uniform runs' sum 13, reached by 4 of the 20 splits
    reading, p_value = prediction_reading(scores([0.1, 0.2, 0.95], [0.9, 1.0, 0.8]))
    assert reading == IN_THE_MEAN and p_value == pytest.approx(0.2)


def test_a_softmax_family_that_reads_higher_refutes_it():
    reading, p_value = prediction_reading(scores([0.9, 1.0, 1.0], [0.5, 0.6, 0.7]))
    assert reading == REFUTED and p_value == pytest.approx(1.0)


def test_the_reports_lines_name_the_runs_not_in_yet_and_the_reading():
    lines = grid_failures.prediction_lines([grid_run("softmax", 0.0), grid_run("constant", 1.0)])
    assert "| softmax family | softmax | 0% |" in lines and "| uniform draws | constant | 100% |" in lines
    assert "| softmax family | max_boltzmann | not run yet |" in lines
    assert lines[-1] == "Reading with 2 of 6 runs: **pending**."


def failed(start_index, hit="", end="collision", start_set="test"):
    return dataclasses.replace(episode("greedy", start_set, 53, end, (0, 0, 0, 53), start_index), hit=hit,
                               end_place="B1-C1")


def test_a_runs_failed_test_episodes_are_counted_by_place_unless_one_lacks_it():
    deep = "parked car on B1-C1 45 m from B1, 0.9 m right of the centre-line"
    episodes = [failed(1, deep), failed(2, deep), failed(9, "a tree"), failed(3, end="offroad"),
                failed(4, deep, start_set="train"), episode("greedy", "test", 100, "cap", (0, 0, 0, 100), 5)]
    assert grid_failures.failed_test_sites(episodes) == {deep: 2, "a tree": 1, "offroad on B1-C1": 1}
    older = [*episodes, episode("greedy", "test", 9, "collision", (0, 0, 0, 9), 6)]  # no place recorded
    assert grid_failures.failed_test_sites(older) is None
    assert grid_failures.failed_test_sites(episodes[-1:]) == {}


def test_the_sites_table_names_each_runs_most_frequent_place_and_the_runs_without_places():
    def run(name, sites):
        return SimpleNamespace(run=SimpleNamespace(name=name), test_sites=sites)

    runs = [run("softmax-b1000-s1", Counter({"a tree": 1, "parked car X": 5, "offroad on C1": 1})),
            run("constant-b1000-s2", Counter()), run("bmc-b1000-s0", None)]
    lines = grid_failures.site_lines(runs)
    assert lines[2:] == ["| Run | Test failures | Where most happened | There | Elsewhere |", "|---|---:|---|---:|---|",
                         "| softmax-b1000-s1 | 7 | parked car X | 5 | a tree (1); offroad on C1 (1) |",
                         "| constant-b1000-s2 | 0 | – | – | – |", "", "Not recorded: bmc-b1000-s0."]
    assert grid_failures.site_lines(runs[2:])[-1] == "No run's evaluation records where its failures happened yet."
