"""The study at a fixed budget (deploy/studies/study.py): which configuration a run is, its table and verdicts."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from common.config_values import flat_items, load_config
from deploy.studies import study
from tests.study_runs import write_run


def items(**overrides):
    return flat_items(load_config("local", overrides=overrides))


def test_a_run_is_the_configuration_its_config_sets():
    assert study.configuration_of(items()) == "paper"
    assert study.configuration_of(items(**{"learner.n_step": 3})) == "nstep3"
    assert study.configuration_of(items(**{"learner.stored_state": True, "learner.burn_in": 2})) == "stored-burnin2"
    assert study.configuration_of(items(**{"learner.stored_state": True})) == "stored"
    assert study.configuration_of(items(**{"pace.env_steps_per_update": 2})) == "ratio2"
    combined = {"learner.stored_state": True, "learner.burn_in": 2, "learner.precision": "auto"}
    assert study.configuration_of(items(**combined)) == "combination"
    assert study.configuration_of(items(**{**combined, "learner.precision": "bfloat16"})) is None  # forced, not auto
    assert study.configuration_of(items(**{"learner.n_step": 3, "learner.batch_size": 20})) is None  # no such one
    assert study.configuration_of(items(**{"exploration.strategy": "softmax"})) == "paper"  # not a study option


def test_the_report_reads_each_seed_at_the_budget_and_says_which_differences_the_seeds_support(tmp_path):
    runs = tmp_path / "runs"
    write_run(runs, "a", 0, {}, [50, 100, 300])
    write_run(runs, "b", 1, {}, [60, 120, 400])
    write_run(runs, "c", 0, {"learner.n_step": 3}, [80, 1_200, 1_500])  # drives at 2,000 updates
    write_run(runs, "d", 1, {"learner.n_step": 3}, [90, 900, 1_100])  # at 3,000
    write_run(runs, "e", 0, {"learner.stored_state": True}, [90, 200, 350])  # one seed only
    write_run(runs, "f", 1, {"pace.env_steps_per_update": 2.0}, [1_100, 900, 1_300])  # drives, swings, drives
    costs = tmp_path / "costs.json"
    costs.write_text(json.dumps({"rows": [{"configuration": "nstep3", "updates_per_s": 2.0},
                                          {"configuration": "paper", "updates_per_s": 2.5}]}))
    found = study.find_runs([runs])
    assert [(run.configuration, run.seed) for run in found] == [("paper", 0), ("paper", 1), ("nstep3", 0),
                                                                ("nstep3", 1), ("stored", 0), ("ratio2", 1)]
    report = study.write_report(found, 2_500, costs, tmp_path / "out").read_text()
    with (tmp_path / "out" / "study.csv").open() as handle:
        rows = {(row["configuration"], row["seed"]): row for row in csv.DictReader(handle)}
    assert rows[("paper", "0")]["updates_at_budget"] == "2000" and float(rows[("paper", "0")]["test_mean_length"]) == 100
    assert rows[("nstep3", "0")]["updates_to_drive"] == "2000"
    # the window, 500 to 2,500: the policies of 1,000 and 2,000
    assert float(rows[("nstep3", "0")]["window_mean_length"]) == pytest.approx((80 + 1_200) / 2)
    assert rows[("nstep3", "0")]["window_policies"] == "2"
    assert float(rows[("nstep3", "0")]["derived_hours_to_drive"]) == pytest.approx(round(2000 * 0.5 / 3600, 2))
    assert rows[("nstep3", "1")]["updates_to_drive"] == ""  # at 3,000, past the budget
    assert rows[("nstep3", "0")]["updates_drive_held_from"] == "2000"
    # it fell back under 1,000 at 2,000; read at the budget (2,000), it has not held driving
    assert rows[("ratio2", "1")]["updates_to_drive"] == "1000" and rows[("ratio2", "1")]["updates_drive_held_from"] == ""
    assert "nstep3 against paper: mean +940 steps; seeds apart (by chance alone 1 time in 3)" in report
    assert "stored against paper" in report and "not asked (1 vs 2 seeds" in report
    window_verdicts = report.split("And over the window, 500–2,500 updates:")[1]
    assert "nstep3 against paper: mean +485 steps; seeds apart" in window_verdicts  # (640 + 495) / 2 - (75 + 90) / 2
    assert (tmp_path / "out" / "study.png").stat().st_size > 0


def test_a_run_of_no_configuration_is_left_out_with_a_line(tmp_path, capsys):
    write_run(tmp_path, "x", 0, {"learner.n_step": 3, "learner.batch_size": 20}, [10])
    assert study.find_runs([tmp_path]) == []
    assert "fits no configuration" in capsys.readouterr().err


def test_a_curve_without_a_policy_near_the_budget_has_no_reading_there(tmp_path):
    """A curve evaluated only in parts (1,000 to 3,000, then 9,000) is not read at 6,000 from its 3,000 policy."""
    write_run(tmp_path, "a", 0, {}, [50, 60, 70, 0, 0, 0, 0, 0, 900])
    write_run(tmp_path, "b", 0, {"learner.n_step": 3}, [50, 60, 70, 80, 90, 100])
    runs = study.find_runs([tmp_path])
    runs[0].test_rows = [row for row in runs[0].test_rows if int(row["updates"]) in (1000, 2000, 3000, 9000)]
    report = study.write_report(runs, 6_000, None, tmp_path / "out").read_text()
    assert "| paper | 0 | – | no policy kept within 1,000 updates of the budget | – | – |" in report
    assert runs[1].window(6_000) and runs[0].window(3_000) and not runs[0].window(9_000)  # 7,000 and 8,000 missing
    assert "nstep3 against paper: not asked (no reading at the budget on one side)" in report


def test_the_committed_study_rebuilds_from_its_committed_runs(tmp_path, monkeypatch):
    root = study.ROOT
    monkeypatch.chdir(root)  # the report names its folders as given, relative to the clone
    args = json.loads((root / "results" / "study" / study.REPORT_ARGS).read_text())
    costs = Path(args["costs"]) if args["costs"] else None
    study.write_report(study.find_runs([Path(folder) for folder in args["folders"]]), args["budget"], costs, tmp_path,
                       [Path(folder) for folder in args["folders"]])
    for name in ("study.md", "study.csv"):
        assert (tmp_path / name).read_text() == (root / "results" / "study" / name).read_text(), name


def test_a_damaged_run_folder_is_left_out_with_a_line(tmp_path, capsys):
    write_run(tmp_path, "a", 0, {}, [50])
    (tmp_path / "a-s0" / "config.toml").write_text("[learner\nbroken")
    assert study.find_runs([tmp_path]) == []
    assert "left out" in capsys.readouterr().err
    write_run(tmp_path, "b", 1, {}, [50])
    curve = tmp_path / "b-s1" / "curve.csv"
    curve.write_text(curve.read_text().replace(",50,", ",fifty,"))  # a damaged cell
    assert study.find_runs([tmp_path]) == []
    assert "b-s1 left out" in capsys.readouterr().err


def test_a_curves_line_does_not_bridge_policies_that_were_not_evaluated():
    xs, ys = study.broken_at_gaps([1000, 2000, 5000, 5400, 6000], [1.0, 2.0, 5.0, 5.4, 6.0])
    assert xs[:2].tolist() == [1000.0, 2000.0] and xs[3:].tolist() == [5000.0, 5400.0, 6000.0]
    assert np.isnan(xs[2]) and np.isnan(ys[2]) and ys[3:].tolist() == [5.0, 5.4, 6.0]
