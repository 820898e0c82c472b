"""Greedy learning curves: the learner keeps policies at its cadence, a kept file reads back into the
network, `evaluate --curve` evaluates the kept policies once each, and the time to drive."""

import csv
import json
import logging
import math
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from actor.evaluation.command import build_parser, main
from actor.evaluation import EvaluationError
from actor.evaluation.curve import (CURVE_TRIALS, crowding_warning, curve_config, curve_summary, first_reaching,
                                    late_curves, of_kind, read_curve, summary_lines, trained_with, warn_if_crowding)
from actor.evaluation.curve_figure import unbridged
from actor.evaluation.workers import torch_threads_per_worker
from common.analysis.tables import COVERAGE_COLUMNS
from common.checkpoint import CheckpointError, KeptPolicy
from common.sim_config import EvaluationConfig
from common.config_values import from_dict, load_config, to_dict, to_toml
from common.network import D3RQN, load_numpy_weights
from common.schema.fields import ConfigError
from common.run_dir import RunDir, RunStatus
from learner.keep import PolicyKeeper
from learner.service import CPU_LABEL, LearnerService
from tests.test_learner_resume import batches, config, train  # noqa: F401 (config: a fixture)
from tests.test_status_lines import FakeClock

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
# a curve committed before evaluate counted the streets and junctions of an episode
OLD_CURVE = Path(__file__).resolve().parents[1] / "results" / "time-to-drive" / "ttd-float32-s0" / "curve.csv"


def learner(config, clock=time.monotonic, keep_every=0, keep_every_s=0.0) -> LearnerService:
    config.learner.keep_every, config.learner.keep_every_s = keep_every, keep_every_s
    service = LearnerService(config, clock=clock)
    service.start_updates()
    return service


def kept(config) -> list[int]:
    return [updates for updates, _ in RunDir.of(config).kept_policies()]


# --- the learner keeps policies ----------------------------------------------------------------------------

def test_the_learner_keeps_a_policy_every_n_updates_and_at_the_end(config):
    process = learner(config, keep_every=2)
    for batch in batches(5):
        train(process, batch)
        process.keep_policy_if_due()
    process.keeper.wait()
    assert kept(config) == [2, 4]
    process.keep_last_policy()
    assert kept(config) == [2, 4, 5]
    run = RunDir.of(config)
    assert [path.name for _, path in run.kept_policies()] == ["policy-u0000002.pt", "policy-u0000004.pt",
                                                             "policy-u0000005.pt"]
    assert not list(run.policies.glob(".*"))  # written whole: no temporary file left behind
    second = KeptPolicy.load(run.policy(2))
    assert (second.updates, second.env_steps) == (2, 140)  # the replay's count after the second batch
    assert second.config["learner"]["keep_every"] == 2


def test_the_learner_keeps_a_policy_every_period_by_its_clock(config):
    clock = FakeClock()
    process = learner(config, clock, keep_every_s=10.0)
    for batch in batches(6):
        clock.now += 4.0  # an update takes 4 s
        train(process, batch)
        process.keep_policy_if_due()
    process.keep_last_policy()  # the last one was just kept: not again
    run = RunDir.of(config)
    assert kept(config) == [3, 6]
    assert [KeptPolicy.load(path).wall_s for _, path in run.kept_policies()] == [12.0, 24.0]


def test_without_a_cadence_nothing_is_kept(config):
    process = learner(config)
    for batch in batches(2):
        train(process, batch)
        process.keep_policy_if_due()
    process.keep_last_policy()
    assert kept(config) == []


def test_a_resumed_run_s_wall_time_carries_on(config):
    clock = FakeClock()
    first = learner(config, clock, keep_every=1)
    train(first, batches(1)[0])
    clock.now += 100.0
    first.checkpoint()
    later = FakeClock()
    later.now = 5000.0  # another session: its clock has its own origin
    resumed = LearnerService(config, clock=later)
    resumed.resume()
    later.now += 30.0
    train(resumed, batches(2)[1])
    resumed.keep_policy_if_due()
    resumed.keeper.wait()
    assert KeptPolicy.load(RunDir.of(config).policy(2)).wall_s == pytest.approx(130.0)


def test_a_kept_policy_names_the_gpu_before_the_cpu_where_the_learner_trained_on_one(config, monkeypatch):
    process = learner(config, keep_every=1)
    train(process, batches(1)[0])
    process.keep_policy_if_due()
    process.keeper.wait()
    assert KeptPolicy.load(RunDir.of(config).policy(1)).cpu == CPU_LABEL
    train(process, batches(2)[1])
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda device=None: "NVIDIA H200")
    process.learner.device = torch.device("cuda")  # what the label reads (the update ran on the CPU)
    process.keep_policy_if_due()
    process.keeper.wait()
    assert KeptPolicy.load(RunDir.of(config).policy(2)).cpu == f"NVIDIA H200, {CPU_LABEL}"


# --- the kept file ---------------------------------------------------------------------------------------------

def test_a_kept_policy_reads_back_into_the_network(config):
    process = learner(config, keep_every=1)
    train(process, batches(1)[0])
    process.keep_policy_if_due()
    process.keeper.wait()
    path = RunDir.of(config).policy(1)
    payload = torch.load(path, weights_only=True)
    # no target; the precision the learner updated in (learner.precision auto differs by CPU); which weights
    assert set(payload) == {"format", "updates", "env_steps", "wall_s", "cpu", "config", "online", "precision",
                            "kind"}
    assert payload["kind"] == "online"
    policy = KeptPolicy.load(path)
    assert policy.precision == process.learner.precision and policy.precision in ("float32", "bfloat16")
    network = D3RQN(from_dict(policy.config).network)
    load_numpy_weights(network, policy.weights())
    shape = (1, 2, config.network.frame_height, config.network.frame_width, 3)
    frames = torch.randint(0, 256, shape, dtype=torch.uint8)
    with torch.no_grad():
        assert torch.equal(network(frames)[0], process.learner.online(frames)[0])


@pytest.mark.parametrize("encoding", ["float16", "bfloat16"])
def test_a_policy_kept_in_16_bits_is_the_trained_one_rounded(config, encoding):
    config.learner.keep_encoding = encoding
    process = learner(config, keep_every=1)
    train(process, batches(1)[0])
    process.keep_policy_if_due()
    process.keeper.wait()
    policy = KeptPolicy.load(RunDir.of(config).policy(1))
    assert policy.encoding == encoding and policy.config["learner"]["keep_encoding"] == encoding
    trained = process.learner.online_weights()
    dtype = getattr(torch, encoding)
    for name, array in policy.weights().items():  # widened back: float32 holding exactly the rounded weights
        assert array.dtype == np.float32
        assert np.array_equal(array, torch.from_numpy(trained[name]).to(dtype).float().numpy())


def test_weights_a_16_bit_encoding_cannot_hold_are_kept_in_float32_with_a_warning(tmp_path, caplog):
    run = RunDir(tmp_path / "run")
    keeper = PolicyKeeper(run, cadence=None, encoding="float16")
    online = {"w": torch.tensor([1.0, 70_000.0])}  # beyond float16's 65,504
    caplog.set_level(logging.WARNING, logger="learner")
    keeper.keep([KeptPolicy(updates=3, env_steps=9, wall_s=1.0, cpu="Test CPU", config={}, online=online)])
    keeper.wait()
    kept_back = KeptPolicy.load(run.policy(3))
    assert kept_back.encoding == "float32" and kept_back.online["w"].tolist() == [1.0, 70_000.0]
    assert keeper.failed == 0
    assert any("kept in float32, not float16" in record.message for record in caplog.records)


def test_a_damaged_or_foreign_policy_file_is_a_clear_error(config, tmp_path):
    process = learner(config, keep_every=1)
    train(process, batches(1)[0])
    process.keep_policy_if_due()
    process.keeper.wait()
    path = RunDir.of(config).policy(1)
    good = path.read_bytes()
    path.write_bytes(good[:len(good) // 2])
    with pytest.raises(CheckpointError, match="cannot read kept policy"):
        KeptPolicy.load(path)
    checkpoint = process.checkpoint()
    with pytest.raises(CheckpointError, match="is not a kept policy"):
        KeptPolicy.load(checkpoint)
    payload = torch.load(checkpoint, weights_only=True)
    torch.save({"format": "d3rqn kept policy", "updates": -1, "env_steps": 3, "wall_s": math.nan, "cpu": "x",
                "config": payload["config"], "online": payload["learner"]["online"]}, path)
    with pytest.raises(CheckpointError, match="updates, wall_s missing or malformed"):
        KeptPolicy.load(path)
    for precision in ("float64", 16, ["float32"]):
        torch.save({"format": "d3rqn kept policy", "updates": 1, "env_steps": 3, "wall_s": 1.0, "cpu": "x",
                    "config": payload["config"], "online": payload["learner"]["online"], "precision": precision}, path)
        with pytest.raises(CheckpointError, match=": precision missing or malformed"):
            KeptPolicy.load(path)


def test_keeping_options_are_checked_and_set_by_the_presets_and_the_grid():
    assert (load_config("paper").learner.keep_every, load_config("paper").learner.keep_every_s) == (0, 0.0)
    assert load_config("local").learner.keep_every == 1_000 and load_config("smoke").learner.keep_every == 100
    with pytest.raises(ConfigError, match="learner.keep_every_s"):
        load_config("paper", overrides={"learner.keep_every_s": -1})
    assert load_config("local").learner.keep_encoding == "float32"  # as trained, unless asked
    with pytest.raises(ConfigError, match="learner.keep_encoding"):
        load_config("paper", overrides={"learner.keep_encoding": "int8"})


# --- the curve ----------------------------------------------------------------------------------------------

def tiny_config(runs_dir):
    return load_config("smoke", overrides={"run.name": "tiny", "run.runs_dir": str(runs_dir),
                                           "network.lstm_units": 16, "evaluation.workers": 1,
                                           "evaluation.envs_per_worker": 5})


def keep(config, updates: int, precision: str = "", kind: str = "online") -> None:
    """A kept policy as the learner writes it, with weights of its own (precision "": as kept before the
    learner recorded it)."""
    torch.manual_seed(updates)
    online = D3RQN(config.network).state_dict()
    KeptPolicy(updates=updates, env_steps=40 * updates, wall_s=2.0 * updates, cpu="Test CPU", config=to_dict(config),
               online=online, precision=precision, kind=kind).save(RunDir.of(config).policy(updates, kind))


def read_rows(path):
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


# one trial per start: the default (5) is test_the_curve_takes_five_trials_per_start_unless_told's
CURVE_FLAGS = ["--evaluation.episodes_per_start", "1", "--evaluation.max_steps", "8"]


def test_the_curve_evaluates_each_kept_policy_once_and_skips_a_damaged_one(tmp_path, capsys, caplog, monkeypatch):
    config = tiny_config(tmp_path)
    run = RunDir.of(config)
    keep(config, 10)
    run.policy(20).write_bytes(b"half a file")
    caplog.set_level(logging.WARNING, logger="evaluate")
    lowered = []  # the test process keeps its priority: os.nice is asked, and answers as from niceness 6
    monkeypatch.setattr("actor.evaluation.command.os.nice", lambda steps: lowered.append(steps) or 6 + steps)
    main(["--curve", str(run.root), *CURVE_FLAGS, "--nice", "1"])
    assert lowered == [1]
    assert any("skipped" in record.message and "policy-u0000020.pt" in record.message for record in caplog.records)
    rows = read_rows(run.curve / "curve.csv")
    assert [(row["updates"], row["start_set"]) for row in rows] == [("10", "train"), ("10", "test")]
    first = rows[1]
    assert (first["env_steps"], first["wall_s"], first["kept_file"], first["trained_on"],
            first["trained_precision"]) == ("400", "20.0", "policy-u0000010.pt", "Test CPU", "")
    assert int(first["nice"]) == 7 and first["policy"] == "greedy" and first["episodes"] == "10"
    for statistic in ("mean_length", "cfr"):
        assert float(first[f"{statistic}_low"]) <= float(first[statistic]) <= float(first[f"{statistic}_high"])
    assert 1 <= float(first["mean_length"]) <= 8
    assert (run.curve / "curve.png").read_bytes()[:8] == PNG_MAGIC
    summary = json.loads((run.curve / "curve_summary.json").read_text())
    assert summary["drive"]["reached"] is None and summary["policies"] == 1
    out = capsys.readouterr().out
    assert "first greedy test mean length >= 1,000 steps: not reached in 1 kept policies" in out

    keep(config, 30, "bfloat16")  # the run went on, on a CPU where learner.precision auto chose bfloat16
    main(["--curve", str(run.root), *CURVE_FLAGS])
    errors = capsys.readouterr().err  # the new one and the damaged one, not the one evaluated already
    assert "curve: 2/2 kept policies" in errors and "policy-u0000020.pt skipped" in errors
    rows_after = read_rows(run.curve / "curve.csv")
    assert rows_after[:2] == rows and [row["updates"] for row in rows_after[2:]] == ["30", "30"]
    assert [row["trained_precision"] for row in rows_after] == ["", "", "bfloat16", "bfloat16"]

    run.policy(20).unlink()
    written = (run.curve / "curve.csv").stat().st_mtime_ns
    summary_path = run.curve / "curve_summary.json"
    summary_path.write_text(json.dumps({"evaluated_on": "Another CPU", "policies": 1}))  # stopped before its summary
    main(["--curve", str(run.root), *CURVE_FLAGS])
    assert "nothing new: all 2 kept policies are in" in capsys.readouterr().err
    assert (run.curve / "curve.csv").stat().st_mtime_ns == written
    redrawn = json.loads(summary_path.read_text())  # from the CSV, naming the CPU that evaluated, not this one
    assert redrawn["policies"] == 2 and redrawn["evaluated_on"] == "Another CPU"
    summary_path.unlink()
    main(["--curve", str(run.root), *CURVE_FLAGS])
    assert json.loads(summary_path.read_text())["evaluated_on"] == "not recorded"


def test_follow_evaluates_the_policies_a_training_run_keeps_until_its_stack_stops(tmp_path, monkeypatch):
    config = tiny_config(tmp_path)
    run = RunDir.of(config)
    run.root.mkdir(parents=True)
    RunStatus(phase="training", pids={"learner": os.getpid()}).write(run.status)
    keep(config, 10)
    waits = []

    def the_run_goes_on(seconds):  # while the follower waits: one more policy, then the stack finishes
        waits.append(seconds)
        keep(config, 30)
        RunStatus(phase="finished").write(run.status)

    monkeypatch.setattr("actor.evaluation.command.time.sleep", the_run_goes_on)
    main(["--curve", str(run.root), *CURVE_FLAGS, "--sets", "test", "--follow", "5"])
    assert waits == [5.0]
    assert [row["updates"] for row in read_rows(run.curve / "curve.csv")] == ["10", "30"]
    # a stack killed outright leaves "training" with dead pids: nothing to follow, one pass
    RunStatus(phase="training", pids={"learner": 2**22 + 17}).write(run.status)
    keep(config, 40)
    main(["--curve", str(run.root), *CURVE_FLAGS, "--sets", "test", "--follow"])
    assert waits == [5.0] and read_rows(run.curve / "curve.csv")[-1]["updates"] == "40"

    # the train set afterwards: at multiples of 20 updates only (a long run's coarse curve), then of the last
    # policies (to choose one on the train starts), then of all: only the rows lacking are added, each
    # policy's train row first
    main(["--curve", str(run.root), *CURVE_FLAGS, "--sets", "train", "--every", "20"])
    assert [row["updates"] for row in read_rows(run.curve / "curve.csv") if row["start_set"] == "train"] == ["40"]
    main(["--curve", str(run.root), *CURVE_FLAGS, "--sets", "train", "--from-updates", "30"])
    assert [(row["updates"], row["start_set"]) for row in read_rows(run.curve / "curve.csv")] == [
        ("10", "test"), *((updates, name) for updates in ("30", "40") for name in ("train", "test"))]
    main(["--curve", str(run.root), *CURVE_FLAGS, "--sets", "train,test"])
    assert [(row["updates"], row["start_set"]) for row in read_rows(run.curve / "curve.csv")] == [
        (updates, name) for updates in ("10", "30", "40") for name in ("train", "test")]
    for wrong in (["--from-updates", "41"], ["--every", "7"], ["--every", "0"]):  # nothing such kept: an error
        with pytest.raises(SystemExit):
            main(["--curve", str(run.root), *CURVE_FLAGS, *wrong])

    # a coarse curve followed from the start waits for a policy at its multiple, not only for any policy
    def the_coarse_run_goes_on(seconds):
        waits.append(seconds)
        keep(config, 60)
        RunStatus(phase="finished").write(run.status)

    RunStatus(phase="training", pids={"learner": os.getpid()}).write(run.status)
    keep(config, 50)
    monkeypatch.setattr("actor.evaluation.command.time.sleep", the_coarse_run_goes_on)
    main(["--curve", str(run.root), *CURVE_FLAGS, "--sets", "test", "--every", "60", "--follow", "5"])
    assert waits == [5.0, 5.0] and read_rows(run.curve / "curve.csv")[-1]["updates"] == "60"


def test_a_follower_of_a_run_that_stopped_before_a_policy_at_its_multiple_ends_without_error(tmp_path, capsys):
    config = tiny_config(tmp_path)
    run = RunDir.of(config)
    run.root.mkdir(parents=True)
    RunStatus(phase="finished").write(run.status)
    keep(config, 10)
    main(["--curve", str(run.root), *CURVE_FLAGS, "--sets", "test", "--every", "2000", "--follow", "5"])
    assert "nothing to follow" in capsys.readouterr().err
    assert not (run.curve / "curve.csv").exists()
    with pytest.raises(SystemExit):  # asked for without --follow, the same span is an error
        main(["--curve", str(run.root), *CURVE_FLAGS, "--sets", "test", "--every", "2000"])


def test_the_shadow_kinds_are_rows_of_their_own_and_the_online_summary_stays_the_online_one(tmp_path, capsys):
    config = tiny_config(tmp_path)
    run = RunDir.of(config)
    keep(config, 10)
    keep(config, 20)
    keep(config, 20, kind="target")
    keep(config, 30, kind="ema")
    main(["--curve", str(run.root), *CURVE_FLAGS, "--sets", "test"])
    summary = json.loads((run.curve / "curve_summary.json").read_text())
    main(["--curve", str(run.root), *CURVE_FLAGS, "--kinds", "target,ema", "--from-updates", "20"])
    rows = read_rows(run.curve / "curve.csv")
    assert [(row["updates"], row["kind"], row["start_set"]) for row in rows] == [
        ("10", "online", "test"), ("20", "online", "test"), ("20", "target", "train"), ("20", "target", "test"),
        ("30", "ema", "train"), ("30", "ema", "test")]
    assert {row["kept_file"] for row in rows if row["kind"] != "online"} == {"policy-u0000020.pt", "policy-u0000030.pt"}
    again = json.loads((run.curve / "curve_summary.json").read_text())
    assert again == summary  # the online one (no policy kept from 20,000 updates: no late curve)
    assert [(row["updates"], row["start_set"]) for row in read_curve(run.curve / "curve.csv")] == [
        ("10", "test"), ("20", "test")]
    capsys.readouterr()
    main(["--curve", str(run.root), *CURVE_FLAGS, "--kinds", "target", "--from-updates", "20"])
    assert "nothing new" in capsys.readouterr().err  # each kind's rows are its own: not evaluated again
    with pytest.raises(SystemExit):
        main(["--curve", str(run.root), *CURVE_FLAGS, "--kinds", "mean"])  # none kept of that kind
    assert "no kept mean policies" in capsys.readouterr().err
    rows[0]["kind"] = "best"  # a damaged cell: a clear error, not a crash when the curve is rewritten
    with (run.curve / "curve.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    with pytest.raises(EvaluationError, match="kind 'best' is not one of"):
        read_curve(run.curve / "curve.csv")
    with pytest.raises(SystemExit):
        main(["--curve", str(run.root), *CURVE_FLAGS, "--kinds", "target,best"])
    assert "--kinds: choose from online, target, ema, mean" in capsys.readouterr().err


def test_the_late_curve_of_each_kind_is_its_test_rows_from_20000_updates_by_hand():
    def row(updates, kind, start_set, cfr, length):
        return {"updates": str(updates), "kind": kind, "start_set": start_set, "cfr": str(cfr),
                "mean_length": str(length)}
    rows = [row(18_000, "online", "test", 1.0, 2_000), row(20_000, "online", "test", 0.6, 1_500),
            row(22_000, "online", "test", 0.2, 900), row(22_000, "online", "train", 0.0, 10),
            row(20_000, "ema", "test", 0.9, 1_800), row(22_000, "ema", "test", 0.8, 1_700)]
    late = late_curves(rows)
    assert list(late) == ["online", "ema"]
    assert late["online"]["policies"] == 2 and late["online"]["test_cfr_mean"] == pytest.approx(0.4)
    assert late["online"]["test_cfr_min"] == 0.2 and late["online"]["test_mean_length_mean"] == 1_200
    assert late["ema"]["test_cfr_mean"] == pytest.approx(0.85) and late["ema"]["test_cfr_min"] == 0.8
    lines = summary_lines({**curve_summary([{**r, "env_steps": "1", "wall_s": "1", "kept_file": "f",
                                             "trained_on": "cpu", "nice": "0"} for r in of_kind(rows)]),
                           "late_curve": late})
    assert ("late curve of the ema policies (2 kept from 20,000 updates): test CFR 85.0% on average, 80% at the "
            "least; mean length 1,750") in lines


def test_a_curve_from_before_the_coverage_and_precision_columns_reads_and_takes_new_rows(tmp_path, capsys):
    old_rows = read_rows(OLD_CURVE)
    assert not {*COVERAGE_COLUMNS, "trained_precision"} & set(old_rows[0])
    rows = read_curve(OLD_CURVE)
    assert len(rows) == len(old_rows) and {row[column] for row in rows for column in COVERAGE_COLUMNS} == {"nan"}
    assert {row["trained_precision"] for row in rows} == {""} and {row["kind"] for row in rows} == {"online"}
    assert (rows[0]["updates"], rows[0]["start_set"], rows[0]["mean_length"]) == ("1000", "train", "70.18")

    config = tiny_config(tmp_path)
    run = RunDir.of(config)
    run.curve.mkdir(parents=True)
    shutil.copy(OLD_CURVE, run.curve / "curve.csv")
    keep(config, 30)  # a kept policy the old curve lacks (its first is at 1,000 updates)
    main(["--curve", str(run.root), *CURVE_FLAGS])
    assert "curve: 1/1 kept policies" in capsys.readouterr().err
    after = read_rows(run.curve / "curve.csv")
    assert after[2:] == [{**row, "trained_precision": "", "kind": "online",
                          **{column: "nan" for column in COVERAGE_COLUMNS}} for row in old_rows]
    assert [(row["updates"], row["start_set"]) for row in after[:2]] == [("30", "train"), ("30", "test")]
    for row in after[:2]:  # 8 steps of 1 m stay on the start street, 20 m or more from the junction ahead
        assert [float(row[column]) for column in COVERAGE_COLUMNS] == [1.0, 1.0, 1.0, 0.0, 0.0, 0.0]


def test_a_curve_with_a_damaged_cell_is_a_clear_error(tmp_path):
    path = tmp_path / "curve.csv"
    path.write_text("updates,env_steps,wall_s,start_set,mean_length,cfr\n1000,4000,10.0,test,abc,0.0\n")
    with pytest.raises(EvaluationError, match="is not a curve of evaluate --curve.*abc"):
        read_curve(path)


def test_a_run_without_kept_policies_is_a_clear_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--curve", str(tmp_path / "nothing")])
    assert exit_info.value.code == 1
    assert "no kept online policies in" in capsys.readouterr().err


def test_the_curve_takes_five_trials_per_start_unless_told():
    saved = to_dict(load_config("smoke"))
    assert curve_config(saved, build_parser().parse_args(["--curve", "x"])).evaluation.episodes_per_start == CURVE_TRIALS
    flags = build_parser().parse_args(["--curve", "x", "--evaluation.episodes_per_start", "7"])
    assert curve_config(saved, flags).evaluation.episodes_per_start == 7


def test_a_curve_followed_beside_a_run_takes_one_torch_thread_per_worker_unless_told():
    saved = to_dict(load_config("smoke"))
    parse = build_parser().parse_args
    assert curve_config(saved, parse(["--curve", "x"])).evaluation.torch_threads == 0  # the cores, divided
    assert curve_config(saved, parse(["--curve", "x", "--follow"])).evaluation.torch_threads == 1
    told = parse(["--curve", "x", "--follow", "--evaluation.torch_threads", "2"])
    assert curve_config(saved, told).evaluation.torch_threads == 2


def test_a_follower_that_would_crowd_the_learners_cores_says_so_and_what_to_do():
    assert crowding_warning(1, 1, 1, 2) is None  # 1 + 1 threads on 2 cores
    assert crowding_warning(2, 2, 1, 4) is None
    told = crowding_warning(0, 1, 1, 2)  # torch's default: every core
    assert "2 + 1 > 2 cores" in told and "learner.torch_threads 0: every core" in told
    assert "--learner.torch_threads 1" in told and "after training" in told
    assert "3 + 2 > 4 cores" in crowding_warning(3, 2, 1, 4)
    assert "fewer workers" in crowding_warning(1, 2, 1, 2)  # the follower alone fills the cores


def test_following_a_run_warns_in_one_line_when_its_learner_and_the_follower_crowd_the_cores(tmp_path, caplog):
    run = RunDir(tmp_path / "run")
    run.root.mkdir()
    follow = build_parser().parse_args(["--curve", str(run.root), "--follow"])  # the smoke preset: 1 worker
    with caplog.at_level(logging.WARNING, logger="evaluate"):
        assert warn_if_crowding(run, follow, cores=2) is None  # no config.toml: said, nothing to weigh
        assert "cannot weigh" in caplog.text
        caplog.clear()
        run.config.write_text(to_toml(load_config("smoke")))  # learner.torch_threads 0: both cores
        warning = warn_if_crowding(run, follow, cores=2)
        assert [record.getMessage() for record in caplog.records] == [warning]
        assert "1 worker(s) x 1 thread(s): 2 + 1 > 2 cores" in warning
        caplog.clear()
        run.config.write_text(to_toml(load_config("smoke", overrides={"learner.torch_threads": 1})))
        assert warn_if_crowding(run, follow, cores=2) is None and not caplog.records
        two = build_parser().parse_args(["--curve", str(run.root), "--follow", "--evaluation.workers", "2"])
        assert "1 + 2 > 2 cores" in warn_if_crowding(run, two, cores=2)


def test_the_workers_torch_threads_are_the_option_or_the_cores_divided(monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1, 2, 3})
    assert torch_threads_per_worker(EvaluationConfig(), 2) == 2
    assert torch_threads_per_worker(EvaluationConfig(), 8) == 1
    assert torch_threads_per_worker(EvaluationConfig(torch_threads=1), 1) == 1
    with pytest.raises(ConfigError, match="torch_threads"):
        load_config("smoke", overrides={"evaluation.torch_threads": -1})


# --- the time to drive ---------------------------------------------------------------------------------------

def row(updates, start_set, mean_length, cfr):
    return {"updates": str(updates), "env_steps": str(4 * updates), "wall_s": str(updates / 10), "kept_file": f"u{updates}",
            "trained_on": "Test CPU", "nice": "10", "start_set": start_set, "mean_length": str(mean_length),
            "cfr": str(cfr)}


def test_the_time_to_drive_is_the_first_test_row_that_reaches_it():
    rows = [row(3000, "test", 1200, 0.6), row(1000, "train", 1500, 0.9), row(1000, "test", 400, 0.1),
            row(2000, "test", 1000, 0.3), row(2000, "train", 800, 0.2)]  # out of order, as a CSV may not be
    drive = first_reaching(rows, "mean_length", 1000)
    assert (drive["updates"], drive["env_steps"], drive["wall_s"], drive["trained_on"]) == (
        2000, 8000, 200.0, "Test CPU, precision not recorded")
    assert first_reaching(rows, "cfr", 0.5)["updates"] == 3000  # the train set's 90% at 1,000 does not count
    summary = curve_summary(rows)
    assert (summary["policies"], summary["last_updates"], summary["nice"]) == (3, 3000, [10])
    assert summary_lines(summary)[0].startswith("first greedy test mean length >= 1,000 steps: update 2,000, "
                                                "8,000 env steps, 3:20 of wall time, trained on Test CPU, "
                                                "precision not recorded")


def test_the_machine_and_precision_a_curve_was_trained_with_by_spans_of_its_kept_policies():
    rows = [row(1000, "test", 50, 0), row(1000, "train", 60, 0), row(2000, "test", 70, 0), row(3000, "test", 80, 0),
            row(4000, "test", 90, 0), row(5000, "test", 95, 0)]
    assert trained_with(rows) == "Test CPU, precision not recorded" and trained_with([]) == ""
    for item, (cpu, precision) in zip(rows, [("AMD EPYC", "float32")] * 3 + [("Intel Xeon", "bfloat16")] * 2
                                      + [("AMD EPYC", "float32")]):
        item.update(trained_on=cpu, trained_precision=precision)
    assert trained_with(rows[:3]) == "AMD EPYC, float32"
    assert trained_with(rows) == ("AMD EPYC, float32 to 2,000 updates; Intel Xeon, bfloat16 from 3,000; "
                                  "AMD EPYC, float32 from 5,000")


def test_a_drive_is_held_from_the_first_policy_after_which_none_falls_below():
    lengths = {1000: 300, 2000: 1230, 3000: 744, 4000: 1069, 5000: 1323, 6000: 1368}  # a swinging curve
    rows = [row(updates, "test", length, 0.0) for updates, length in lengths.items()] + [row(2000, "train", 0, 0)]
    assert first_reaching(rows, "mean_length", 1000)["updates"] == 2000
    assert first_reaching(rows, "mean_length", 1000, held=True)["updates"] == 4000
    assert first_reaching(rows + [row(7000, "test", 503, 0.0)], "mean_length", 1000, held=True) is None
    lines = summary_lines(curve_summary(rows))
    assert lines[1].startswith("first greedy test mean length >= 1,000 steps at every kept policy from there on: "
                               "update 4,000")


def test_the_policy_to_ship_is_chosen_on_the_training_starts_not_the_test_starts():
    rows = [row(1000, "train", 1500, 0.7), row(1000, "test", 1900, 0.95),  # the test set's best
            row(2000, "train", 1600, 0.8), row(2000, "test", 1400, 0.6),
            row(3000, "train", 1700, 0.8), row(3000, "test", 1200, 0.5)]  # ties on train CFR: the longer
    chosen = curve_summary(rows)["chosen_on_train"]
    assert (chosen["updates"], chosen["train_cfr"], chosen["test_cfr"], chosen["test_mean_length"]) == (
        3000, 0.8, 0.5, 1200.0)
    assert summary_lines(curve_summary(rows))[-2] == (
        "chosen on the training starts (highest train CFR, then mean length): update 3,000 (u3000): train CFR 80%, "
        "mean length 1,700; test CFR 50%, mean length 1,200")
    assert curve_summary([row(1000, "test", 400, 0.1)])["chosen_on_train"] is None
    assert "among" not in summary_lines(curve_summary(rows))[-2]  # all of them
    partly = curve_summary([row(500, "test", 1950, 1.0)] + rows)  # the earlier one only on the test starts
    assert (partly["chosen_on_train"]["updates"], partly["chosen_on_train"]["among"]) == (3000, 3)
    assert summary_lines(partly)[-2].startswith(
        "chosen on the training starts among the 3 of 4 kept policies evaluated on them (1,000-3,000 updates) "
        "(highest train CFR, then mean length): update 3,000")
    assert "no kept policy was evaluated on them" in summary_lines(curve_summary([row(1000, "test", 400, 0.1)]))[-2]
    assert curve_summary([row(1000, "train", 400, 0.1)])["chosen_on_train"]["test_cfr"] is None
    # the test rows read back from the CSV (strings) beside train rows just evaluated (numbers)
    read_back = [{**r, "updates": int(r["updates"])} if r["start_set"] == "train" else r for r in rows]
    mixed = curve_summary(read_back)["chosen_on_train"]
    assert (mixed["updates"], mixed["test_cfr"], mixed["of"]) == (3000, 0.5, 3)


def test_a_curve_that_never_drives_says_so():
    rows = [row(1000, "test", 400, 0.1), row(2000, "test", 999, 0.49)]
    assert first_reaching(rows, "mean_length", 1000) is None and first_reaching(rows, "cfr", 0.5) is None
    lines = summary_lines(curve_summary(rows))
    assert lines[2] == "first greedy test CFR >= 50%: not reached in 2 kept policies (up to update 2,000)"
    train_only = summary_lines(curve_summary([row(1000, "train", 2000, 1.0)]))
    assert train_only[0] == "first greedy test mean length >= 1,000 steps: the test set was not evaluated"


def test_evaluate_checkpoint_takes_a_kept_policy_file(tmp_path):
    config = tiny_config(tmp_path)
    keep(config, 30)
    policy = RunDir.of(config).policy(30)
    main(["--checkpoint", str(policy), "--sets", "test", "--no-random-baseline", *CURVE_FLAGS])
    out = RunDir.of(config).evaluation  # the run's evaluation folder, not one under policies/
    facts = json.loads((out / "facts.json").read_text())
    assert facts["source"] == f"kept policy {policy}" and (facts["updates"], facts["env steps"]) == ("30", "1200")
    assert [row["start_set"] for row in read_rows(out / "summary.csv")] == ["test"]


def test_a_sets_line_does_not_bridge_policies_evaluated_on_the_other_set_only():
    rows = [row(updates, "test", 100, 0.0) for updates in (1000, 2000, 3000, 4000)]
    rows += [row(updates, "train", 100, 0.0) for updates in (1000, 2000, 4000)]
    train = [entry for entry in rows if entry["start_set"] == "train"]
    assert [[int(entry["updates"]) for entry in segment] for segment in unbridged(train, rows)] == [[1000, 2000], [4000]]
    assert len(unbridged(rows[:4], rows)) == 1 and unbridged([], rows) == []
