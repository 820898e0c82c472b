"""The grid's report (deploy/studies/grid_report.py) on exported runs made by hand: each figure against values
computed by hand."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest

from common.config_values import load_config, to_toml
from deploy.studies import grid_claims, grid_costs, grid_failures, grid_report
from tests.grid_runs import fake_evaluation

CURVE = {1000: 200, 2000: 1200, 3000: 800, 4000: 1100, 6000: 1500}  # updates: greedy test mean length


def exported_run(top: Path, strategy: str, seed: int, starts: list[int], curve: dict[int, float] = CURVE,
                 capacity: int = 1000, summary: dict | None = None) -> Path:
    """An exported grid run: its greedy test curve, its choice, and its chosen policy's evaluation (one
    greedy episode per start, of these lengths; 100 reaches the cap)."""
    folder = top / f"{strategy}-b{capacity}-s{seed}"
    (folder / "curve").mkdir(parents=True)
    config = load_config("drive", overrides={"run.name": folder.name, "exploration.strategy": strategy,
                                             "run.seed": seed, "replay.capacity": capacity})
    (folder / "config.toml").write_text(to_toml(config))
    (folder / "cell.json").write_text(json.dumps({"strategy": strategy, "capacity": capacity, "seed": seed,
                                                  "options": "paper", "updates": 6000}))
    (folder / "choice.json").write_text(json.dumps({"updates": 6000, "among": [2000, 3000, 4000, 6000]}))
    with (folder / "curve" / "curve.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=["updates", "env_steps", "wall_s", "kept_file", "trained_on",
                                                    "nice", "start_set", "mean_length", "cfr"])
        writer.writeheader()
        for updates, length in curve.items():
            writer.writerow({"updates": updates, "env_steps": 28_000 + 4 * updates, "wall_s": updates / 2,
                             "kept_file": f"policy-u{updates:07d}.pt", "trained_on": "AMD EPYC", "nice": 0,
                             "start_set": "test", "mean_length": length, "cfr": 0.5})
    fake_evaluation(folder / "evaluation", starts, updates=6000, progress=True)
    # trained past the chosen policy
    (folder / "summary.json").write_text(json.dumps({"updates": 6050, **(summary or {})}))
    return folder


def test_a_runs_row_reads_its_curve_and_its_chosen_policy(tmp_path):
    exported_run(tmp_path, "bmc", 0, [100, 100, 100, 50])
    (run,) = grid_report.read_runs([tmp_path])
    row = grid_report.run_row(run)
    assert (row["updates_to_drive"], row["env_steps_to_drive"], row["drive_held_from"]) == (2000, 36_000, 4000)
    # trapezoids: (200+1200)/2 + (1200+800)/2 + (800+1100)/2 over 1,000 each, (1100+1500)/2 over 2,000; / 5,000
    assert row["curve_mean_length"] == pytest.approx((700 + 1000 + 950 + 2600) * 1000 / 5000)
    assert row["test_cfr"] == pytest.approx(0.75) and (row["chosen_updates"], row["updates"]) == (6000, 6050)
    # a street per 25 steps and a junction fewer: (4 + 4 + 4 + 2) / 4 and (3 + 3 + 3 + 1) / 4
    assert (row["test_streets"], row["test_junctions"]) == (3.5, 2.5)
    assert run.start_cfr.tolist() == [1.0, 1.0, 1.0, 0.0]
    assert row["trained_on"] == "AMD EPYC, precision not recorded"  # a curve from before the learner recorded it


def test_a_run_that_never_drove_has_no_time_to_drive():
    assert grid_report.curve_mean([{"updates": 1000, "mean_length": 5}]) == 5
    assert math.isnan(grid_report.curve_mean([]))


def test_a_strategys_row_pools_its_seeds_and_takes_the_iqm_over_seeds_and_starts(tmp_path):
    for seed, starts in enumerate(([100, 100, 100, 50], [100, 50, 50, 50], [100, 100, 50, 40])):
        exported_run(tmp_path, "bmc", seed, starts)
    (row,) = grid_report.strategy_rows(grid_report.read_runs([tmp_path]), grid_report.Bootstrap(replicates=200))
    # 12 scores, six 1s and six 0s: the middle six (three cut from each end) are three 0s and three 1s
    assert row["iqm_test_cfr"] == pytest.approx(0.5)
    assert row["iqm_test_cfr_low"] <= 0.5 <= row["iqm_test_cfr_high"]
    assert row["test_cfr"] == pytest.approx(np.mean([0.75, 0.25, 0.5]))
    assert row["drove"] == "3/3" and row["updates_to_drive"] == "2000;2000;2000"
    assert row["drive_held_from"] == "4000;4000;4000"
    # lengths 40, 50 x5, 100 x6: the middle six are three 50s and three 100s
    assert row["iqm_test_length"] == pytest.approx(75.0)
    assert row["iqm_test_length_low"] <= 75.0 <= row["iqm_test_length_high"]
    assert row["paper_test_cfr"] == pytest.approx(0.8671)


def test_the_claims_pool_strategies_and_three_seeds_a_side_can_only_lean(tmp_path):
    for seed in range(3):
        exported_run(tmp_path, "bmc", seed, [100, 100, 100, 100])
        exported_run(tmp_path, "constant", seed, [50, 50, 50, 50])
    runs = grid_report.read_runs([tmp_path])
    first, second = grid_claims.claim_readings(runs, grid_report.Bootstrap(replicates=200))
    for reading in (first, second):
        # every BMC run above every constant run: P = 1, and the least p-value of 3 runs against 3, 1/20
        assert reading["improvement"] == 1.0 and reading["p_value"] == pytest.approx(0.05)
        assert reading["smallest_p"] == pytest.approx(0.05) and reading["reading"] == "a lean"
    (pair,) = grid_claims.pair_readings(runs, grid_report.Bootstrap(replicates=200))
    assert (pair["first"], pair["second"], pair["improvement"]) == ("constant", "bmc", 0.0)


def test_a_claim_the_runs_contradict_is_read_the_other_way_round_too(tmp_path):
    for seed in range(4):
        exported_run(tmp_path, "bmc", seed, [50, 50, 50, 50])
        exported_run(tmp_path, "constant", seed, [100, 100, 100, 100])
    lines = grid_claims.claims_lines(grid_report.read_runs([tmp_path]), grid_report.Bootstrap(replicates=200))
    claim_1 = lines.index(next(line for line in lines if line.startswith("- Claim 1")))
    assert "**can't tell**" in lines[claim_1] and "P(better > worse) = 0.000" in lines[claim_1]
    # every constant run above every BMC run: one-sided 1/C(8, 4) = 1/70, doubled 0.0286
    assert lines[claim_1 + 1] == ("  - The other way round (the worse group ahead, read after the fact): "
                                  "**supported**; two-sided p = 0.0286, P(worse > better) = 1.000 [1.000, 1.000].")


def test_the_pairs_worth_more_seeds_are_those_whose_interval_lies_off_even_the_farthest_first():
    pairs = [{"first": "constant", "second": "bmc", "improvement": 0.6, "low": 0.45, "high": 0.7, "runs": (3, 3)},
             {"first": "constant", "second": "max_boltzmann", "improvement": 0.7, "low": 0.55, "high": 0.8,
              "runs": (3, 3)},
             {"first": "vdbe", "second": "max_boltzmann", "improvement": 0.2, "low": 0.1, "high": 0.35,
              "runs": (3, 2)},
             {"first": "vdbe", "second": "softmax", "improvement": 1.0, "low": 1.0, "high": 1.0, "runs": (1, 1)}]
    chosen = grid_claims.pairs_off_even(pairs)
    # margins: 0.05 and 0.15 off 0.5; the first straddles 0.5 and one run each has no interval
    assert [(row["first"], row["second"]) for row in chosen] == [("vdbe", "max_boltzmann"),
                                                                 ("constant", "max_boltzmann")]
    (line,) = grid_claims.more_seeds_lines(chosen)
    assert "vdbe < max_boltzmann; constant > max_boltzmann" in line
    assert "--strategies vdbe,max_boltzmann --buffers 1000 --seeds 3,4" in line
    assert "0.0040" in line  # 1 / C(10, 5) = 1/252
    assert "no pair" in grid_claims.more_seeds_lines([])[0]


def test_a_policy_kept_at_a_stop_is_not_on_the_curve(tmp_path):
    # stopped at 1,500 updates with a policy that reached the cap: the curve, scheduled every 1,000, drove at
    # 2,000 all the same
    exported_run(tmp_path, "bmc", 0, [100, 100, 100, 50], curve={**CURVE, 1500: 2000})
    (run,) = grid_report.read_runs([tmp_path])
    assert [int(row["updates"]) for row in run.test_rows] == sorted(CURVE)
    assert grid_report.run_row(run)["updates_to_drive"] == 2000


def test_the_report_is_written_from_exported_runs_alone(tmp_path):
    for seed in range(2):
        exported_run(tmp_path / "runs", "softmax", seed, [100, 50, 50, 50])
    exported_run(tmp_path / "runs", "vdbe", 0, [50, 50, 50, 50], curve={1000: 100, 2000: 300})
    paths = grid_report.report_on([tmp_path / "runs"], tmp_path / "out", grid_report.Bootstrap(replicates=100))
    assert sorted(path.name for path in paths) == ["curves.png", "grid.md", "grid_runs.csv", "grid_strategies.csv",
                                                  "time_to_drive.png"]
    page = (tmp_path / "out" / "grid.md").read_text()
    assert "| vdbe | 1000 | paper | 0 | 6,050 | not reached |" in page
    assert "| softmax | 1000 | paper | 2 | 2/2 | 2,000, 2,000 | 4,000, 4,000 |" in page
    assert "| softmax | 1000 | paper | 0 | 6,050 | 2,000 (36,000; 0.28 h) | 4,000 |" in page  # 1,000 s of run time
    assert "Claim 1" in page and "needs 4 seeds a side" in page
    # one seed, or one run a side, resamples nothing: no interval of zero width is shown
    assert ("| vdbe | 1000 | paper | 1 | 0/1 | not reached | not reached | 200 | 50 (one seed) | 0.0% | 0.0% (one seed) "
            "| 61.8% |") in page  # per strategy
    assert "| vdbe | softmax | 0.38 [0.38, 0.38] |" in page  # 1 against 2 alike runs: a width of zero, measured
    exported_run(tmp_path / "runs", "bmc", 0, [100, 50, 50, 50])
    grid_report.report_on([tmp_path / "runs"], tmp_path / "out", grid_report.Bootstrap(replicates=100))
    assert "| vdbe | bmc | 0.38 (one run each) |" in (tmp_path / "out" / "grid.md").read_text()
    with pytest.raises(ValueError, match="no finished grid run"):
        grid_report.report_on([tmp_path / "out"], tmp_path / "again")


def test_a_damaged_export_is_left_out_with_a_line(tmp_path):
    exported_run(tmp_path, "bmc", 0, [100, 100, 100, 50])
    damaged = exported_run(tmp_path, "bmc", 1, [100, 50, 50, 50])
    (damaged / "curve" / "curve.csv").write_text("updates,mean_length\nten,x\n")
    broken_choice = exported_run(tmp_path, "bmc", 2, [100, 50, 50, 50])
    (broken_choice / "choice.json").write_text("[1, 2]")
    lines = []
    runs = grid_report.read_runs([tmp_path], warn=lines.append)
    assert [item.run.seed for item in runs] == [0]
    assert any("bmc-b1000-s1" in line for line in lines)


def test_the_committed_grid_rebuilds_from_its_committed_runs(tmp_path):
    """results/grid/ is what deploy/studies/grid_report.py makes of results/grid/runs/, on a fresh clone too."""
    committed = Path(__file__).resolve().parents[1] / "results" / "grid"
    grid_report.report_on([committed / "runs"], tmp_path, warn=lambda line: pytest.fail(line))
    for name in ("grid.md", "grid_runs.csv", "grid_strategies.csv"):
        assert (tmp_path / name).read_text() == (committed / name).read_text(), name


def test_the_soak_across_the_grid_by_hand():
    rows = [{"run": "a", "hours": 2.0, "restarts": 1, "folder_mb": 900.0, "actor-0_mb_per_hour": 10.0,
             "actor-0_last_mb": 800.0, "replay_rest_mb_per_hour": math.nan},
            {"run": "b", "hours": 1.5, "restarts": 0, "folder_mb": 1200.0, "actor-0_mb_per_hour": 30.0,
             "actor-0_last_mb": 900.0, "replay_rest_mb_per_hour": 4.0},
            {"run": "c", "hours": 0.5, "restarts": 0, "folder_mb": 100.0, "actor-0_mb_per_hour": -5.0,
             "actor-0_last_mb": 700.0, "replay_rest_mb_per_hour": 2.0}]
    lines = grid_costs.soak_lines(rows)
    assert lines[0] == "3 runs, 4.0 hours of run time in all, 1 restart; the largest run folder b (1,200 MB)."
    assert "| actor-0 | +10.0 | +30.0 | 800 | 900 |" in lines  # medians and largest of the three
    assert "| replay_rest | +3.0 | +4.0 | - | - |" in lines  # the nan left out; no end figure
    assert grid_costs.soak_lines([]) == ["No run of the grid has a soak yet."]


def test_the_machine_time_by_hand(tmp_path):
    recorded = exported_run(tmp_path, "bmc", 0, [100, 100, 100, 50])
    (recorded / "steps.csv").write_text("step,started,wall_s,cpu,cores,outcome,peak_mb\n"
                                        "train,0,3600,AMD EPYC,2,stopped,3000\nresume,0,1800,Intel Xeon,2,done,3500\n"
                                        "curve,0,900,Intel Xeon,2,done,1800\nchoose,0,0,Intel Xeon,2,done,nan\n"
                                        "evaluate,0,900,Intel Xeon,2,done,2100\n")
    exported_run(tmp_path, "bmc", 1, [100, 50, 50, 50])
    partly = exported_run(tmp_path, "bmc", 2, [100, 50, 50, 50])  # begun before the steps were recorded
    (partly / "steps.csv").write_text("step,started,wall_s,cpu,cores,outcome\nresume,0,360,AMD EPYC,2,done\n"
                                      "curve,0,720,AMD EPYC,2,done\n")
    with_steps, without, resumed = sorted(grid_report.read_runs([tmp_path]), key=lambda item: item.run.seed)
    row = grid_costs.machine_row(with_steps, None)
    assert (row["training_h"], row["reading_h"]) == (1.5, 0.5)
    assert row["machines"] == ["AMD EPYC (2 cores)", "Intel Xeon (2 cores)"]
    assert (row["training_peak_mb"], row["reading_peak_mb"]) == (3500.0, 2100.0)  # the most of each; nan unread
    unrecorded = grid_costs.machine_row(without, 2.25)
    assert (unrecorded["training_h"], unrecorded["reading_h"]) == (2.25, None)
    assert unrecorded["machines"] == ["AMD EPYC, precision not recorded (its kept policies)"]
    part = grid_costs.machine_row(resumed, 3.0)
    assert (part["training_h"], part["reading_h"]) == (3.0, 0.2)  # training by its soak, not its 0.1 h resume
    lines = grid_costs.machine_lines([row, unrecorded, part])
    assert lines[0] == ("Training: 6.8 h over 3 runs (1 recorded step by step in steps.csv, 2 by the soak of a run "
                        "begun before). Curve, choice and evaluation: 0.7 h over the 2 runs that recorded them. "
                        "Machines: AMD EPYC (2 cores); AMD EPYC, precision not recorded (its kept policies); "
                        "Intel Xeon (2 cores).")
    assert lines[2] == ("Peak memory of a run's processes at once: training (every role) 3,500 MB at most "
                        "(bmc-b1000-s0; 1 run); curve, choice and evaluation 2,100 MB at most (bmc-b1000-s0; 1 run).")
    assert "| bmc-b1000-s0 | 1.50 | 0.50 | 3,500 / 2,100 | AMD EPYC (2 cores); Intel Xeon (2 cores) |" in lines
    assert "| bmc-b1000-s2 | 3.00 (soak) | 0.20 | – / – | AMD EPYC (2 cores) |" in lines  # steps.csv before peaks


def test_a_damaged_or_partial_soak_summary_does_not_stop_the_report(tmp_path):
    runs = [exported_run(tmp_path, "bmc", seed, [100, 100, 100, 50]) for seed in range(3)]
    memory = {"actor-0": {"second_half_mb_per_hour": 2.0, "last_mb": 800.0}}
    for folder, summary in zip(runs, ['{"hours": ', json.dumps({"hours": 1.0, "restarts": 0, "folder_bytes_last": 5e6,
                                                                  "memory": memory, "replay_held": None})]):
        (folder / "soak").mkdir()
        (folder / "soak" / "soak_summary.json").write_text(summary)
    said = []
    rows = grid_costs.soak_rows(sorted(grid_report.read_runs([tmp_path]), key=lambda item: item.run.seed), said.append)
    assert [row["run"] for row in rows] == ["bmc-b1000-s1"] and math.isnan(rows[0]["replay_rest_mb_per_hour"])
    assert len(said) == 1 and "bmc-b1000-s0" in said[0]
    blank = {"run": "x", "training_recorded": False, "training_h": None, "reading_h": None, "machines": [],
             "training_peak_mb": None, "reading_peak_mb": None}
    assert grid_costs.machine_lines([blank])[-1] == "| x | – | – | – / – | – |"


def test_the_share_of_actions_off_greedy_counts_only_the_episodes_its_actors_counted(tmp_path):
    counted = exported_run(tmp_path, "softmax", 0, [100, 100, 100, 50])
    (counted / "training.csv").write_text("return,length,epsilon,off_greedy\n"
                                          "1.0,40,1.0,-1\n2.0,100,1.0,7\n3.0,300,1.0,13\n"  # 20 of 400
                                          "4.0,10,1.0,11\n5.0,10,1.0,-3\n")  # damaged counts: left out
    (counted / "learner.csv").write_text("updates,loss_abs_diff\n")
    older = exported_run(tmp_path, "bmc", 0, [100, 100, 100, 50])
    (older / "training.csv").write_text("return,length,epsilon\n1.0,40,1.0\n")  # exported before the count
    (older / "learner.csv").write_text("updates,loss_abs_diff\n")
    exported_run(tmp_path, "vdbe", 0, [100, 100, 100, 50])  # exported without curves
    runs = grid_report.read_runs([tmp_path])
    shares = {item.run.strategy: grid_report.run_row(item)["off_greedy_share"] for item in runs}
    assert shares == {"softmax": 0.05, "bmc": "", "vdbe": ""}
    assert grid_report.explored_lines(runs)[-1] == "| softmax | 1000 | paper | 5.00% (seed 0) |"
    assert grid_report.explored_lines(runs[:0])[0].startswith("No run's actors counted")


def test_the_test_starts_table_gives_each_runs_cfr_per_start_and_the_starts_most_runs_fail(tmp_path):
    exported_run(tmp_path, "bmc", 0, [100, 100, 100, 50])  # one episode per start; 100 reaches the cap
    exported_run(tmp_path, "softmax", 0, [100, 50, 100, 50])
    lines = grid_failures.start_lines(grid_report.read_runs([tmp_path]))
    assert lines[2:] == ["| Run | 0 | 1 | 2 | 3 |", "|---|---:|---:|---:|---:|",
                         "| bmc-b1000-s0 | 100% | 100% | 100% | 0% |", "| softmax-b1000-s0 | 100% | 0% | 100% | 0% |",
                         "| mean over runs | 100% | 50% | 100% | 0% |", "| runs below 50% | 0 | 1 | 0 | 2 |"]
