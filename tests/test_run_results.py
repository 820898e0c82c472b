"""Finished runs exported small (deploy/studies/run_results.py) and the report rebuilt from them alone (deploy/studies/report.py):
what an export holds, how exports from several folders merge, and a report with no run folder left."""

from __future__ import annotations

import csv
import math
import shutil
from pathlib import Path

import pytest

from common.analysis.tables import COVERAGE, COVERAGE_COLUMNS
from common.config_values import load_config, to_toml
from common.run_dir import RunDir
from deploy.studies import report
from deploy.studies.run_results import (LEARNER_CSV, TRAINING_CSV, ExportError, collect, export_run, read_exported)
from tests.grid_runs import fake_evaluation, make_smoke_run
from tests.test_experiments import assert_png, learner_report, record, write_log


def evaluated_run(root, strategy: str = "bmc", seed: int = 0, lengths=(100, 50), updates: int = 120):
    """A run folder of the smoke preset (capacity 50) with a config, an evaluation, a summary and a log."""
    name = f"{strategy}-b50-s{seed}"
    run = make_smoke_run(root / name, 1000, evaluated=True, updates=updates, strategy=strategy, seed=seed)
    fake_evaluation(run / "evaluation", list(lengths), updates=updates)
    evaluation_config = load_config("smoke", overrides={"exploration.strategy": strategy, "run.seed": seed,
                                                        "evaluation.episodes_per_start": 3})
    (run / "evaluation" / "config.toml").write_text(to_toml(evaluation_config))  # as evaluate writes it
    (run / "summary.json").write_text('{"run": "%s", "updates": %d, "env_steps_per_update": 4.0}' % (name, updates))
    write_log(run / "traffic.mcap", name, strategy, 50,
              [record(10, 5.0, 1.0), learner_report(50, 0.2), record(12, 6.0, 0.5, off_greedy=3),
               learner_report(100, 0.1)])
    return RunDir(run)


def test_an_export_holds_the_evaluation_config_summary_and_curves_and_nothing_large(tmp_path):
    run = evaluated_run(tmp_path / "runs")
    folder = export_run(run, tmp_path / "exported")
    assert folder == tmp_path / "exported" / "bmc-b50-s0"
    assert sorted(path.relative_to(folder).as_posix() for path in folder.rglob("*") if path.is_file()) == [
        "config.toml", "evaluation/config.toml", "evaluation/episodes.csv", "evaluation/facts.json",
        "evaluation/summary.csv",
        "evaluation/summary.md", "learner.csv", "summary.json", "training.csv"]
    assert (folder / TRAINING_CSV).read_text().splitlines() == [
        "return,length,epsilon,off_greedy", "5.0,10,1.0,-1", "6.0,12,0.5,3"]
    assert (folder / LEARNER_CSV).read_text().splitlines()[0] == "updates,loss_abs_diff"
    exported = read_exported(folder)
    assert (exported.strategy, exported.capacity, exported.seed, exported.updates) == ("bmc", 50, 0, 120)
    curves = exported.curves()
    assert curves.episode_lengths == [10, 12] and curves.episode_epsilons == [1.0, 0.5]
    assert curves.episode_off_greedy == [-1, 3] and curves.label == "bmc-b50-s0" and curves.capacity == 50
    (folder / TRAINING_CSV).write_text("return,length,epsilon\n5.0,10,1.0\n")  # an export older than the count
    assert read_exported(folder).curves().episode_off_greedy == [-1]


def test_exporting_again_replaces_the_earlier_export(tmp_path):
    run = evaluated_run(tmp_path / "runs", updates=120)
    export_run(run, tmp_path / "exported")
    fake_evaluation(run.evaluation, [100, 100], updates=300)  # evaluated again after more training
    folder = export_run(run, tmp_path / "exported")
    assert read_exported(folder).updates == 300
    assert [path.name for path in (tmp_path / "exported").iterdir()] == ["bmc-b50-s0"]


def test_a_run_without_an_evaluation_is_not_exported(tmp_path):
    run = RunDir(make_smoke_run(tmp_path / "runs" / "bmc-b50-s0", 1000))
    with pytest.raises(ExportError, match="not an evaluated run"):
        export_run(run, tmp_path / "exported")
    assert not (tmp_path / "exported").exists() or not any((tmp_path / "exported").iterdir())


def test_exports_of_two_folders_merge_and_no_run_counts_twice(tmp_path):
    here, there = tmp_path / "here", tmp_path / "there"
    export_run(evaluated_run(tmp_path / "a", "bmc", 0), here)
    export_run(evaluated_run(tmp_path / "a", "softmax", 0), here)
    shutil.copytree(here / "bmc-b50-s0", there / "bmc-b50-s0")  # the same run, copied over: silent
    export_run(evaluated_run(tmp_path / "b", "softmax", 0, lengths=(20, 30)), there)  # trained twice: warned
    export_run(evaluated_run(tmp_path / "b", "bmc", 1), there)  # another seed: merged in
    (there / "notes").mkdir()
    warnings = []
    runs = collect([here, there], warn=warnings.append)
    assert sorted(run.name for run in runs) == ["bmc-b50-s0", "bmc-b50-s1", "softmax-b50-s0"]
    assert {run.name: run.folder.parent for run in runs}["softmax-b50-s0"] == here  # the first folder wins
    twice = [line for line in warnings if "softmax-b50-s0 is in both" in line and "counted once" in line]
    skipped = [line for line in warnings if line.startswith("skipped") and "notes" in line]
    assert len(warnings) == 2 and len(twice) == 1 and len(skipped) == 1


def test_a_folder_named_for_another_run_is_refused(tmp_path):
    folder = export_run(evaluated_run(tmp_path / "runs"), tmp_path / "exported")
    folder.rename(tmp_path / "exported" / "bmc-b50-s9")
    with pytest.raises(ExportError, match="its config says it is run bmc-b50-s0"):
        read_exported(tmp_path / "exported" / "bmc-b50-s9")
    with pytest.raises(ExportError, match="no such folder"):
        collect([tmp_path / "absent"])


def test_the_report_rebuilds_from_exported_runs_alone(tmp_path):
    exported = tmp_path / "committed" / "runs"
    for strategy, seed in (("bmc", 0), ("bmc", 1), ("softmax", 0)):
        export_run(evaluated_run(tmp_path / "machine", strategy, seed, updates=100 + seed), exported)
    shutil.rmtree(tmp_path / "machine")  # no run folder, checkpoint or log is left
    out = tmp_path / "committed"
    assert report.main([str(exported), "--out", str(out)]) == 0
    markdown = (out / "results.md").read_text()
    assert "| BMC | 0, 1 | 100, 101 | 4 |" in markdown  # pooled over both seeds, with each run's updates
    assert "- budget: 20,000 env steps per run" in markdown
    assert "- trials: 3 per start" in markdown  # from the evaluation's config, not the training's
    rows = (out / "results.csv").read_text().splitlines()
    assert len(rows) == 1 + 2 * (3 + 2 + 1)  # per set: bmc pooled + 2 seeds, softmax pooled + 1, random
    assert "## Which differences the intervals support" in markdown
    assert "| BMC, 50 | Softmax, 50 | 2 vs 1 |" in markdown
    compared = (out / "differences.csv").read_text().splitlines()
    assert len(compared) == 1 + 2 * 7  # one pair per start set, seven statistics each (intervals.STATISTICS)
    for name in ("reward_curves.png", "epsilon.png", "loss_differences.png", "reward_bins.png",
                 "performance_profile.png"):
        assert_png(out / name)


def test_a_run_whose_curves_are_damaged_is_left_out_of_the_figures_only(tmp_path):
    exported = tmp_path / "runs"
    folder = export_run(evaluated_run(tmp_path / "machine", "bmc", 0), exported)
    export_run(evaluated_run(tmp_path / "machine", "softmax", 0), exported)
    (folder / TRAINING_CSV).write_text("return,length,epsilon\nabc,1,0.5\n")
    warnings = []
    assert report.main([str(exported), "--out", str(tmp_path / "out")], warn=warnings.append) == 0
    assert any("bmc-b50-s0: left out of the figures" in line for line in warnings)
    assert "| BMC | 0 |" in (tmp_path / "out" / "results.md").read_text()


def test_a_report_of_nothing_is_an_error(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert report.main([str(tmp_path / "empty"), "--out", str(tmp_path / "out")]) == 1
    assert "no exported run" in capsys.readouterr().err


# the comparison's folders (their report is results.md); results/study has its own test (tests/test_study.py)
COMMITTED = sorted(path.parent for path in (Path(__file__).resolve().parents[1] / "results").glob("*/runs")
                   if (path.parent / "results.md").exists())


def csv_rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def same_cell(mine: str, committed: str) -> bool:
    """Equal text, or numbers equal to rounding (another CPU's BLAS may sum in another order)."""
    if mine == committed:
        return True
    try:
        return math.isclose(float(mine), float(committed), rel_tol=1e-9, abs_tol=1e-12)
    except ValueError:
        return False


def without_coverage(rows: list[dict[str, str]]) -> list[dict[str, str]]:
    """The rows less what the committed reports predate: the coverage columns and statistics, which their
    evaluations (episodes.csv without streets and junctions) leave at nan."""
    kept = []
    for row in rows:
        if row.get("statistic") in COVERAGE:
            assert (row["difference"], row["ci_low"], row["ci_high"]) == ("nan", "nan", "nan"), row
            continue
        assert all(row.pop(column) == "nan" for column in COVERAGE_COLUMNS if column in row), row
        kept.append(row)
    return kept


@pytest.mark.parametrize("folder", COMMITTED, ids=[path.name for path in COMMITTED])
def test_the_committed_results_rebuild_from_the_committed_runs_alone(folder, tmp_path):
    # every run the committed report names is in the repository, and its tables come out of them again
    named = next(line for line in (folder / "results.md").read_text().splitlines() if line.startswith("- runs: "))
    runs = collect([folder / "runs"])
    assert sorted(run.name for run in runs) == sorted(named[len("- runs: "):].split(", "))
    assert report.main([str(folder / "runs"), "--out", str(tmp_path)]) == 0
    assert csv_rows(tmp_path / "results.csv")  # a report with rows, so the comparison below has something to hold
    for name in ("results.csv", "differences.csv"):
        mine, committed = without_coverage(csv_rows(tmp_path / name)), csv_rows(folder / name)
        header = [column for column in (tmp_path / name).read_text().splitlines()[0].split(",")
                  if column not in COVERAGE_COLUMNS]
        assert header == (folder / name).read_text().splitlines()[0].split(",") and len(mine) == len(committed)
        for row, committed_row in zip(mine, committed):
            assert all(same_cell(row[key], committed_row[key]) for key in row), (name, row, committed_row)


def test_the_repository_holds_committed_results():
    assert {path.name for path in COMMITTED} >= {"comparison", "main-job-front-camera"}
