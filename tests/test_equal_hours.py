"""Equal hours (deploy/studies/equal_hours.py): runs of one CPU model read at equal measured wall time."""

import csv

import pytest

from deploy.studies import equal_hours
from deploy.studies.study import find_runs
from tests.study_runs import write_run


def two_runs(tmp_path, cpu_b="cpu"):
    """A fast run (a policy every 600 s, driving from its third) and a slow one (every 1,200 s, stopping early)."""
    write_run(tmp_path, "fast", 0, {"learner.stored_state": True, "learner.burn_in": 2, "learner.precision": "auto"},
              [100, 500, 1_200, 1_800, 900, 1_950], seconds_per_policy=600.0)
    write_run(tmp_path, "slow", 0, {}, [80, 300, 1_100], seconds_per_policy=1_200.0, cpu=cpu_b)
    return find_runs([tmp_path])


def test_each_run_is_read_at_each_mark_by_its_last_policy_and_the_span_before_it(tmp_path):
    paper, combination = two_runs(tmp_path)
    assert (paper.configuration, combination.configuration) == ("paper", "combination")
    assert equal_hours.marks([paper, combination], 1800.0) == [1800.0, 3600.0]  # the fast run ends at 3,600 s
    at_hour = equal_hours.reading_at(combination, 3600.0, 1800.0)
    assert at_hour["updates"] == 6000 and at_hour["mean_length"] == 1_950 and at_hour["span_policies"] == 3
    assert at_hour["span_mean_length"] == pytest.approx((1_800 + 900 + 1_950) / 3)  # kept at 2,400, 3,000, 3,600 s
    assert at_hour["span_cfr"] == pytest.approx((0.9 + 0.45 + 0.975) / 3)
    half = equal_hours.reading_at(paper, 1800.0, 1800.0)
    assert half["updates"] == 1000 and half["span_policies"] == 1  # kept at 1,200 s; the next at 2,400
    assert equal_hours.reading_at(paper, 600.0, 1800.0) is None  # nothing kept yet
    assert equal_hours.reading_at(paper, 3700.0, 1800.0) is None  # it stopped at 3,600 s
    paper.test_rows = paper.test_rows[:2]  # as if it had stopped at 2,400 s: a mark there too
    assert equal_hours.marks([paper, combination], 1800.0) == [1800.0, 2400.0, 3600.0]


def test_the_report_writes_its_table_figure_and_milestones(tmp_path):
    runs = two_runs(tmp_path / "runs")
    report = equal_hours.write_report(runs, 1800.0, tmp_path / "out").read_text()
    assert "# Equal hours on cpu" in report
    assert ("| 1:00:00 | 1,100 [1,090, 1,110], CFR 55% (3,000 updates) | 700, CFR 35% (2) | "
            "1,950 [1,940, 1,960], CFR 98% (6,000 updates) | 1,550, CFR 78% (3) |") in report
    assert "combination, seed 0: first greedy test mean length >= 1,000 steps at 30:00 (3,000 updates" in report
    assert "paper, seed 0: first greedy test CFR >= 50% at 1:00:00 (3,000 updates" in report
    assert "paper, seed 0: first greedy test mean length >= 1,000 steps at 1:00:00" in report
    with (tmp_path / "out" / "equal_hours.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 4 and rows[0]["configuration"] == "paper" and rows[0]["updates"] == "1000"
    assert (tmp_path / "out" / "equal_hours.png").stat().st_size > 0


def test_runs_of_two_cpu_models_are_refused_and_one_run_is_too_few(tmp_path, capsys):
    runs = two_runs(tmp_path / "runs", cpu_b="another cpu")
    with pytest.raises(SystemExit, match="measured hours compare only on one CPU model"):
        equal_hours.write_report(runs, 1800.0, tmp_path / "out")
    assert not (tmp_path / "out" / "equal_hours.md").exists()
    with pytest.raises(SystemExit, match="two or more compare"):
        equal_hours.main([str(tmp_path / "runs" / "fast-s0"), "--out", str(tmp_path / "one")])
    with pytest.raises(SystemExit):
        equal_hours.main([str(tmp_path / "runs"), "--every-min", "0", "--out", str(tmp_path / "zero")])
    assert "--every-min must be a positive number" in capsys.readouterr().err


def test_a_curve_without_its_interval_columns_is_one_line_not_a_trace(tmp_path):
    two_runs(tmp_path / "runs")
    curve = tmp_path / "runs" / "slow-s0" / "curve.csv"
    with curve.open() as handle:
        rows = list(csv.DictReader(handle))
    with curve.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=[name for name in rows[0] if name != "mean_length_low"],
                                extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
    with pytest.raises(SystemExit, match="a curve lacks a column or holds a bad value"):
        equal_hours.main([str(tmp_path / "runs"), "--out", str(tmp_path / "out")])
