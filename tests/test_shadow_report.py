"""The shadow policies' report (deploy/studies/shadow_report.py): readings per run and kind, the pairing, and the
rule that ships a kind, on exported runs made by hand."""

import csv
import json

import pytest

from common.analysis.intervals import Bootstrap
from common.config_values import load_config, to_toml
from common.run_dir import RunDir
from deploy.studies import shadow_report
from deploy.studies.run_results import collect
from tests.grid_runs import fake_evaluation

LATE = [20_000, 22_000]
LENGTHS = {1.0: [100, 100], 0.5: [100, 30], 0.0: [30, 30]}  # greedy test and train CFR of fake_evaluation


def exported(folder, strategy, seed, chosen: dict[str, float], late: dict[str, tuple[float, float]]):
    """An exported run: its chosen policies' CFR by kind (both sets), its late curve's CFR by kind at LATE."""
    run = RunDir(folder / f"{strategy}-b2000-s{seed}")
    run.root.mkdir(parents=True)
    config = load_config("drive", overrides={"exploration.strategy": strategy, "run.seed": seed,
                                             "replay.capacity": 2000})
    run.config.write_text(to_toml(config))
    kinds = {kind: {"updates": 29_000, "among": [26_000]} for kind in chosen if kind != "online"}
    (run.root / "choice.json").write_text(json.dumps({"updates": 30_000, "among": [26_000], "kinds": kinds}))
    for kind, cfr in chosen.items():
        fake_evaluation(run.evaluation_of(kind), LENGTHS[cfr], updates=30_000)
    run.curve.mkdir()
    with (run.curve / "curve.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=["updates", "kind", "start_set", "cfr", "mean_length", "env_steps",
                                                    "wall_s"])
        writer.writeheader()
        for kind, values in late.items():
            for updates, cfr in zip(LATE, values):
                for start_set, value in (("train", cfr / 2), ("test", cfr)):  # train rows half the test ones
                    writer.writerow({"updates": updates, "kind": kind, "start_set": start_set, "cfr": value,
                                     "mean_length": 100, "env_steps": 1, "wall_s": 1})
    return run


def three_runs(tmp_path):
    exported(tmp_path, "bmc", 0, {"online": 0.5, "ema": 1.0, "mean": 0.5},
             {"online": (0.2, 0.6), "ema": (0.8, 1.0)})
    exported(tmp_path, "bmc", 1, {"online": 1.0, "ema": 1.0, "mean": 0.0},
             {"online": (0.4, 1.0), "ema": (0.9, 0.9)})
    exported(tmp_path, "softmax", 0, {"online": 0.0, "ema": 0.5, "mean": 1.0},
             {"online": (0.0, 0.4), "ema": (0.6, 0.4)})
    return [reading for run in collect([tmp_path], warn=lambda line: None) for reading in shadow_report.run_readings(run)]


def test_the_readings_by_run_and_kind_by_hand(tmp_path):
    readings = {(r.run, r.kind): r for r in three_runs(tmp_path)}
    online, ema, mean = (readings["bmc-b2000-s0", kind] for kind in ("online", "ema", "mean"))
    assert (online.late_test_mean, online.late_test_min) == (pytest.approx(0.4), 0.2)
    assert (ema.late_train_mean, ema.late_train_min) == (pytest.approx(0.45), 0.4)
    assert (online.chosen_test_cfr, online.chosen_train_cfr, online.chosen_updates) == (0.5, 0.5, 30_000)
    assert (ema.chosen_test_cfr, ema.chosen_updates) == (1.0, 29_000)
    assert mean.late_test_mean is None and mean.chosen_test_cfr == 0.5  # the mean has no late curve


def reading(run, kind, test, train, floor):
    return shadow_report.KindReading(run, "bmc", kind, None, None, None, floor, 30_000, test, train)


def test_the_rule_ships_the_highest_mean_chosen_train_cfr_ties_to_the_floor_then_online():
    # ema reads best on the test starts, target on the train starts: the train starts choose
    readings = [reading("a", "online", 0.5, 0.5, 0.2), reading("a", "target", 0.6, 0.9, 0.2),
                reading("a", "ema", 1.0, 0.7, 0.9), reading("b", "online", 0.5, 0.5, 0.2),
                reading("b", "target", 0.6, 0.9, 0.2), reading("b", "ema", 1.0, 0.7, 0.9)]
    assert shadow_report.shipped_kind(readings) == "target"
    tied = [r if r.kind != "ema" else reading(r.run, "ema", 0.2, 0.9, 0.5) for r in readings]
    assert shadow_report.shipped_kind(tied) == "ema"  # a tie on train CFR: the higher late floor
    same = [reading(run, kind, 0.5, 0.5, 0.2) for run in "ab" for kind in ("target", "online")]
    assert shadow_report.shipped_kind(same) == "online"  # a tie throughout: the paper's
    mean = [reading("a", "online", 0.5, 0.5, 0.2), reading("a", "mean", 0.5, 0.5, None)]
    assert shadow_report.shipped_kind(mean) == "mean"  # its floor is its chosen train CFR, 0.5 > 0.2


def test_a_run_missing_a_kind_does_not_count(tmp_path):
    readings = three_runs(tmp_path)
    assert shadow_report.shipped_kind(readings) == "ema"  # chosen train CFR means 0.5, 0.833, 0.5
    partial = readings + [reading("c", "online", 1.0, 1.0, 1.0)]  # no shadows read: left out
    assert len(shadow_report.complete(partial)) == 3 and shadow_report.shipped_kind(partial) == "ema"


def test_the_page_pairs_each_kind_with_online_and_names_the_shipped_one(tmp_path):
    readings = three_runs(tmp_path)
    lines = shadow_report.report_lines(readings, Bootstrap(replicates=200))
    page = "\n".join(lines)
    # ema against online, chosen test CFR: pairs (1, .5), (1, 1), (.5, 0): two above, one tie; P = (1 + .5 + 1) / 3
    assert "- ema against online, chosen policy's test CFR (K = 10), 3 runs: Wilcoxon two-sided p = 0.500; " \
           "P(ema > online) = 0.833" in page
    assert "late curve's mean test CFR (K = 5), 3 runs" in page and "mean against online, late" not in page
    assert "- ema: chosen test CFR mean 83%, 2 of 3 at 90% or more; late curve's least test CFR 40% at the least, " \
           "2 of 3 runs with none below 80%" in page
    assert page.rstrip().endswith("**Shipped by the rule: ema.**")
    paths = shadow_report.report_on([tmp_path], tmp_path / "out", Bootstrap(replicates=50))
    assert [path.name for path in paths] == ["shadows.md", "shadow_runs.csv"]
