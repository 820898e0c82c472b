"""The grid runner (deploy/grid/experiments.py) and its cells (deploy/grid/grid_cells.py): runs named by cell, the
budget in updates, each step decided from the run folder, the curve's passes, the choice on the train
starts, --cells and --cell, and the export of a grid run."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import threading
from pathlib import Path

import pytest
import torch

import deploy.grid.experiments as experiments
import deploy.grid.grid_job as grid_job
from common.checkpoint import KeptPolicy, save_checkpoint
from common.config_values import load_config, to_toml
from deploy.grid import grid_cells, step_record
from deploy.grid.grid_cells import RunSpec, choice_candidates, choose, curve_wanted, next_step
from deploy.studies.run_results import export_run, read_exported
from common.run_dir import RunDir
from tests.grid_runs import fake_evaluation

BUDGET = 148_000  # the drive preset: updates from 28,000 env steps, 30,000 of them at 4 env steps each
KEPT = list(range(1_000, 30_001, 1_000))


def options(tmp_path: Path, updates: int = 30_000, extra: tuple[str, ...] = ("--preset", "drive")):
    return grid_job.Options(tmp_path, updates, trials=10, actors=None, extra=extra, progress_s=30.0)


def curve_rows(updates: list[int], start_set: str, cfr: dict[int, float] | None = None, kind: str = "online"
               ) -> list[dict]:
    cfr = cfr or {}
    return [{"updates": u, "kind": kind, "env_steps": 28_000 + 4 * u, "wall_s": u / 4,
             "kept_file": f"policy-u{u:07d}.pt", "trained_on": "cpu", "nice": 0, "start_set": start_set,
             "mean_length": 500 + u / 100, "cfr": cfr.get(u, 0.1)} for u in updates]


def write_curve(run: RunDir, rows: list[dict]) -> None:
    run.curve.mkdir(parents=True, exist_ok=True)
    with (run.curve / "curve.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def make_drive_run(folder: Path, env_steps: int | None = None, kept: list[int] = (), curve: list[dict] = (),
             strategy: str = "bmc", seed: int = 0, **learner) -> RunDir:
    """A run folder as the steps leave it: its config, a checkpoint with this clock, kept policies, a curve."""
    run = RunDir(folder)
    folder.mkdir(parents=True, exist_ok=True)
    config = load_config("drive", overrides={"run.name": folder.name, "exploration.strategy": strategy,
                                             "run.seed": seed, **{f"learner.{key}": value for key, value in learner.items()}})
    run.config.write_text(to_toml(config))
    if env_steps is not None:
        save_checkpoint(run.checkpoints, {"clock": {"env_steps": env_steps}, "learner": {"updates": 7}})
    run.policies.mkdir(parents=True, exist_ok=True)
    for updates in kept:
        run.policy(updates).write_bytes(b"kept")
    if curve:
        write_curve(run, list(curve))
    return run


def test_runs_are_named_by_cell_and_seed_and_the_grid_orders_them():
    specs = grid_cells.grid(["bmc", "softmax"], [1000, 2000], [0, 1], ["paper", "nstep3"])
    assert len(specs) == 16
    assert [spec.name for spec in specs[:5]] == ["bmc-b1000-s0", "softmax-b1000-s0", "bmc-b1000-s1",
                                                 "softmax-b1000-s1", "bmc-b1000-nstep3-s0"]
    assert specs[4].option_flags() == ["--learner.n_step", "3"]
    assert RunSpec("bmc", 1000, 0, "stored").option_flags() == ["--learner.stored_state", "true",
                                                                "--learner.burn_in", "0"]
    assert RunSpec("bmc", 1000, 0, "lrdecay").option_flags() == [
        "--learner.lr_decay_from", "20000", "--learner.lr_decay_to", "30000", "--learner.lr_final_scale", "0.1"]
    assert RunSpec("bmc", 1000, 0, "lrdecay").name == "bmc-b1000-lrdecay-s0"


@pytest.mark.parametrize("name", sorted(grid_cells.OPTION_SETS))
def test_every_option_set_is_a_valid_config_on_the_grids_preset(name):
    """Each set's flags, as the runner passes them, load onto the drive preset and take effect."""
    flags = RunSpec("bmc", 1000, 0, name).option_flags()
    config = load_config("drive", overrides=dict(zip((flag[2:] for flag in flags[::2]), flags[1::2])))
    for key, value in grid_cells.OPTION_SETS[name][1].items():
        section, option = key.split(".")
        assert getattr(getattr(config, section), option) == value, key


def test_the_budget_in_updates_sets_each_runs_step_budget_from_its_own_ratio(tmp_path):
    opts = options(tmp_path)
    command = grid_job.stack_command(RunSpec("vdbe", 1000, 2), opts, resume=False)
    flags = dict(zip(command[2::2], command[3::2]))
    assert flags["--preset"] == "drive" and flags["--pace.total_env_steps"] == str(BUDGET)
    assert flags["--run.name"] == "vdbe-b1000-s2" and flags["--exploration.strategy"] == "vdbe"
    ratio2 = grid_job.stack_command(RunSpec("bmc", 1000, 0, "ratio2"), opts, resume=True)
    assert ratio2[-1] == "--resume" and ratio2[ratio2.index("--pace.total_env_steps") + 1] == str(28_000 + 60_000)
    assert ratio2[ratio2.index("--pace.env_steps_per_update") + 1] == "2.0"


@pytest.mark.parametrize("extra, message", [
    (("--preset", "drive", "--replay.capacity", "5"), "set by the grid"),
    (("--preset", "drive", "--pace.total_env_steps=4"), "set by the grid"),
    (("--preset", "drive", "--learner.lr", "oops"), "learner.lr: expected a number"),
    (("--preset", "local"), "pace.start_by steps"),  # the 999 random episodes end at another step per run
    (("--preset", "drive", "--learner.keep_every", "0"), "learner.keep_every"),  # no curve to read
])
def test_config_flags_are_checked_before_anything_runs(tmp_path, extra, message):
    with pytest.raises(grid_cells.ExperimentError, match=message):
        grid_job.check_config_flags(grid_cells.grid(["bmc"], [1000], [0]), options(tmp_path, extra=extra))


def test_the_curve_reads_every_policy_to_20000_updates_then_every_2000():
    wanted = curve_wanted(KEPT + [15_500, 30_004], 1_000)  # 15,500 and 30,004 kept when the run stopped
    assert sorted(wanted) == list(range(1_000, 20_001, 1_000)) + list(range(22_000, 30_001, 2_000))


def test_what_a_run_folder_needs_next(tmp_path):
    assert next_step(tmp_path / "fresh", BUDGET) == "train"
    assert next_step(make_drive_run(tmp_path / "short", 90_000, KEPT[:15]).root, BUDGET) == "resume"
    full = make_drive_run(tmp_path / "full", BUDGET, KEPT, curve_rows(list(range(1_000, 20_001, 1_000)), "test"))
    assert next_step(full.root, BUDGET) == "curve"  # the sparse part is missing
    write_curve(full, curve_rows(sorted(curve_wanted(KEPT, 1_000)), "test"))
    assert next_step(full.root, BUDGET) == "choose"
    write_curve(full, curve_rows(sorted(curve_wanted(KEPT, 1_000)), "test") + curve_rows(KEPT[-5:], "train"))
    choose(full)
    assert next_step(full.root, BUDGET) == "evaluate"
    fake_evaluation(full.evaluation, [100, 50], updates=29_000)  # another policy's evaluation
    assert next_step(full.root, BUDGET) == "evaluate"
    fake_evaluation(full.evaluation, [100, 50], updates=30_000)
    assert next_step(full.root, BUDGET) == "done"
    full.policy(32_000).write_bytes(b"kept")  # trained on past the choice (a larger budget): read it, choose again
    assert next_step(full.root, BUDGET) == "curve"


SHADOWS = list(range(18_000, 30_001, 1_000))  # kept from learner.keep_shadows_from 18,000; read from 20,000


def shadowed_run(tmp_path: Path) -> RunDir:
    """A drive run that kept target and EMA policies from 20,000 updates on, its online curve read; its online
    candidates hold weights that average by hand (26,000 to 30,000: a mean of 28,000)."""
    run = make_drive_run(tmp_path / "run", BUDGET, KEPT, curve_rows(sorted(curve_wanted(KEPT, 1_000)), "test")
                         + curve_rows(KEPT[-5:], "train"), keep_target=True, ema_updates=5_000)
    for updates in KEPT[-5:]:
        KeptPolicy(updates=updates, env_steps=28_000 + 4 * updates, wall_s=1.0, cpu="cpu", config={},
                   online={"w": torch.full((2,), float(updates))}).save(run.policy(updates))
    for kind in ("target", "ema"):
        run.policy_folder(kind).mkdir()
        for updates in SHADOWS:
            run.policy(updates, kind).write_bytes(b"kept")
    return run


def test_a_run_with_shadow_policies_reads_chooses_and_evaluates_each_kind(tmp_path):
    run, opts = shadowed_run(tmp_path), options(tmp_path)
    assert grid_cells.shadow_kinds(run) == ["target", "ema"]
    assert next_step(run.root, BUDGET) == "curve"  # the shadows' curve is missing
    [shadow_pass] = grid_job.curve_commands(run, opts)
    assert shadow_pass[5:shadow_pass.index("--preset")] == [
        "--kinds", "online,target,ema", "--sets", "train,test", "--from-updates", "20000", "--every", "1000"]
    late = sorted(grid_cells.shadow_curve_wanted(run, "target"))  # where the online curve reads, from 20,000
    assert late == list(range(20_000, 30_001, 2_000))
    online_rows = curve_rows(sorted(curve_wanted(KEPT, 1_000)), "test") + curve_rows(KEPT[-5:], "train")
    shadow_rows = [row for kind in ("target", "ema") for start_set in ("train", "test")
                   for row in curve_rows(late, start_set, kind=kind)]
    write_curve(run, online_rows + shadow_rows)
    assert next_step(run.root, BUDGET) == "curve"  # the online policies' train rows at 20,000-24,000 missing
    online_rows += curve_rows([20_000, 22_000, 24_000], "train")
    shadow_rows = [row for row in shadow_rows if row["updates"] != 30_000]
    write_curve(run, online_rows + shadow_rows)
    assert next_step(run.root, BUDGET) == "curve"  # 30,000 of the shadows still missing
    shadow_rows += [row for kind in ("target", "ema") for start_set in ("train", "test")
                    for row in curve_rows([30_000], start_set, kind=kind)]
    write_curve(run, online_rows + shadow_rows)
    assert next_step(run.root, BUDGET) == "choose"
    passes = [command[5:command.index("--preset")] for command in grid_job.choice_commands(run, opts)]
    assert passes == [["--kinds", kind, "--sets", "train", "--from-updates", "26000", "--every", "1000"]
                      for kind in ("target", "ema")]  # 27,000 and 29,000 are off the curve's schedule
    with pytest.raises(grid_cells.ExperimentError, match="lacks train rows of the target policies"):
        choose(run)
    write_curve(run, online_rows + shadow_rows + curve_rows([27_000], "train", {27_000: 0.9}, kind="target")
                + curve_rows([29_000], "train", kind="target") + curve_rows([27_000, 29_000], "train", kind="ema"))
    assert grid_job.choice_commands(run, opts) == []
    choice = choose(run)
    assert choice["updates"] == 30_000 and list(choice["kinds"]) == ["target", "ema", "mean"]
    assert choice["kinds"]["target"]["updates"] == 27_000 and choice["kinds"]["ema"]["updates"] == 30_000
    assert choice["kinds"]["target"]["among"] == KEPT[-5:] == choice["kinds"]["mean"]["among"]
    mean = KeptPolicy.load(run.policy(30_000, "mean"))
    assert mean.kind == "mean" and mean.averaged == tuple(KEPT[-5:]) and mean.online["w"].tolist() == [28_000.0] * 2
    assert next_step(run.root, BUDGET) == "evaluate"
    commands = grid_job.evaluate_commands(run, opts)
    assert [(command[4], command[6]) for command in commands] == [
        (str(run.policy(30_000)), str(run.evaluation)),
        (str(run.policy(27_000, "target")), str(run.root / "evaluation-target")),
        (str(run.policy(30_000, "ema")), str(run.root / "evaluation-ema")),
        (str(run.policy(30_000, "mean")), str(run.root / "evaluation-mean"))]
    assert "--no-random-baseline" not in commands[0] and all("--no-random-baseline" in c for c in commands[1:])
    fake_evaluation(run.evaluation, [100, 50], updates=30_000)
    fake_evaluation(run.evaluation_of("target"), [100, 50], updates=27_000)
    assert next_step(run.root, BUDGET) == "evaluate" and len(grid_job.evaluate_commands(run, opts)) == 2
    fake_evaluation(run.evaluation_of("ema"), [100, 50], updates=30_000)
    fake_evaluation(run.evaluation_of("mean"), [100, 50], updates=30_000)
    assert next_step(run.root, BUDGET) == "done"
    exported = export_run(run, tmp_path / "export")
    assert all((exported / f"evaluation-{kind}" / "summary.csv").is_file() for kind in ("target", "ema", "mean"))
    assert next_step(exported, BUDGET) == "done"
    shutil.rmtree(exported / "evaluation-ema")  # an export lacking a kind's evaluation is not finished
    assert next_step(exported, BUDGET) == "train"


def test_a_choice_without_a_kind_the_run_kept_is_made_again(tmp_path):
    run = shadowed_run(tmp_path)
    (run.root / "choice.json").write_text(json.dumps({"updates": 30_000, "among": KEPT[-5:]}))  # online only
    assert not grid_cells.choice_current(run, grid_cells.read_choice(run))
    (run.root / "choice.json").write_text(json.dumps({"updates": 30_000, "among": KEPT[-5:],
                                                      "kinds": {"best": {"updates": 1}}}))
    assert grid_cells.read_choice(run) is None  # not a kind: made again, never evaluated
    run_without = make_drive_run(tmp_path / "plain", BUDGET, KEPT, keep_target=True)
    assert grid_cells.shadow_kinds(run_without) == []  # on, but none kept (a budget short of keep_shadows_from)


def test_the_policy_is_chosen_on_the_train_starts_among_the_last_five_kept(tmp_path):
    test_cfr = {26_000: 1.0}  # the best on the test starts must not decide
    rows = (curve_rows(KEPT, "test", test_cfr) + curve_rows(KEPT[-5:], "train", {27_000: 0.8, 29_000: 0.8})
            + curve_rows([20_000], "train", {20_000: 1.0}))  # older than the last five: not a candidate
    run = make_drive_run(tmp_path / "run", BUDGET, KEPT, rows)
    choice = choose(run)
    assert choice["updates"] == 29_000 and choice["among"] == KEPT[-5:]  # a tie on CFR: the longer, later one
    assert json.loads((run.root / "choice.json").read_text())["kept_file"] == "policy-u0029000.pt"
    assert choice["train_cfr"] == 0.8 and choice["test_cfr"] == 0.1
    write_curve(run, curve_rows(KEPT, "test") + curve_rows(KEPT[-4:], "train"))
    with pytest.raises(grid_cells.ExperimentError, match="lacks train rows"):
        choose(run)


def test_the_candidates_are_the_scheduled_policies_and_the_last_whatever_the_stops(tmp_path):
    # stopped at 27,688 (a policy kept at the stop), resumed, ended at 30,354: the candidates are those of a run
    # never stopped, 27,000 to 30,000 and the last
    kept = KEPT + [27_688, 30_354]
    run = make_drive_run(tmp_path / "run", BUDGET, sorted(kept))
    assert grid_cells.choice_candidates(run) == [27_000, 28_000, 29_000, 30_000, 30_354]
    run.config.write_text("[learner]\nkeep_every = 0\n")
    with pytest.raises(grid_cells.ExperimentError, match="keep_every"):
        grid_cells.choice_candidates(run)
    run.config.write_text("[learner\n")
    with pytest.raises(grid_cells.ExperimentError, match="cannot read"):
        grid_cells.choice_candidates(run)


def test_the_curve_passes_ask_only_for_what_is_missing(tmp_path):
    opts = options(tmp_path)
    run = make_drive_run(tmp_path / "run", BUDGET, KEPT)
    passes = grid_job.curve_commands(run, opts)
    assert [command[command.index("--sets"):command.index("--sets") + 4] for command in passes] == [
        ["--sets", "test", "--to-updates", "20000"], ["--sets", "test", "--from-updates", "20001"]]
    assert passes[1][passes[1].index("--every") + 1] == "2000"
    assert passes[0][passes[0].index("--every") + 1] == "1000"  # not a policy kept at a stop
    write_curve(run, curve_rows(list(range(1_000, 20_001, 1_000)), "test"))
    assert len(grid_job.curve_commands(run, opts)) == 1
    assert [command[5:] for command in grid_job.choice_commands(run, opts)] == [
        ["--kinds", "online", "--sets", "train", "--from-updates", "26000", "--every", "1000", "--preset", "drive"]]
    (run.root / "choice.json").write_text(json.dumps({"updates": 29_000, "among": KEPT[-5:]}))
    [evaluate] = grid_job.evaluate_commands(run, opts)
    assert evaluate[3:7] == ["--checkpoint", str(run.policy(29_000)), "--out", str(run.evaluation)]
    assert evaluate[-2:] == ["--evaluation.episodes_per_start", "10"]


def test_the_choice_passes_read_its_candidates_and_not_a_policy_kept_at_a_stop(tmp_path):
    run = make_drive_run(tmp_path / "run", BUDGET, [*KEPT[:-3], 27_688, *KEPT[-3:], 30_024])
    assert choice_candidates(run) == [27_000, 28_000, 29_000, 30_000, 30_024]
    spans = [command[7:command.index("--preset")] for command in grid_job.choice_commands(run, options(tmp_path))]
    assert spans == [["--sets", "train", "--from-updates", "27000", "--every", "1000"],
                     ["--sets", "train", "--from-updates", "30024"]]
    write_curve(run, curve_rows([27_000, 28_000, 29_000, 30_000], "train"))
    spans = [command[7:command.index("--preset")] for command in grid_job.choice_commands(run, options(tmp_path))]
    assert spans == [["--sets", "train", "--from-updates", "30024"]]


def test_cells_lists_the_numbered_runs_and_cell_runs_one(tmp_path, capsys):
    argv = ["--strategies", "bmc,softmax", "--seeds", "0,1", "--runs-dir", str(tmp_path)]
    assert experiments.main([*argv, "--cells"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert [line.split()[:2] for line in lines] == [["0", "bmc-b1000-s0"], ["1", "softmax-b1000-s0"],
                                                   ["2", "bmc-b1000-s1"], ["3", "softmax-b1000-s1"]]
    assert all(line.endswith("next: train") for line in lines)
    damaged = make_drive_run(tmp_path / "softmax-b1000-s1", BUDGET, KEPT)
    damaged.checkpoint.write_bytes(b"damaged")  # said in the list; the others are listed all the same
    assert experiments.main([*argv, "--cells"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "next: unreadable (cannot read the step count of" in lines[3] and lines[2].endswith("next: train")
    plan = experiments.parse_arguments([*argv, "--cell", "2"])
    assert [spec.name for spec in plan.specs] == ["bmc-b1000-s1"] and plan.numbers == [2] and plan.grid_size == 4
    assert experiments.main([*argv, "--cell", "4"]) == 2
    assert "the grid has runs 0 to 3" in capsys.readouterr().err


def test_the_learner_gets_the_cores_the_curve_and_other_runs_leave_it():
    assert experiments.thread_flags([], parallel=1, curve_beside=False, cores=2) == []
    assert experiments.thread_flags([], parallel=1, curve_beside=True, cores=2) == ["--learner.torch_threads", "1"]
    assert experiments.thread_flags([], parallel=2, curve_beside=False, cores=8) == ["--learner.torch_threads", "4"]
    assert experiments.thread_flags([], parallel=2, curve_beside=True, cores=2) == ["--learner.torch_threads", "1"]
    assert experiments.thread_flags(["--learner.torch_threads=2"], parallel=2, curve_beside=True, cores=2) == []


def test_a_grid_run_exports_its_cell_choice_curve_and_soak_under_its_cells_name(tmp_path):
    run = make_drive_run(tmp_path / "bmc-b1000-nstep3-s1", BUDGET, KEPT,
                   curve_rows(sorted(curve_wanted(KEPT, 1_000)), "test") + curve_rows(KEPT[-5:], "train"), seed=1)
    grid_cells.write_cell(run, RunSpec("bmc", 1000, 1, "nstep3"), 30_000)
    choose(run)
    fake_evaluation(run.evaluation, [100, 50], updates=30_000)
    run.soak.mkdir()
    (run.soak / "soak.csv").write_text("time\n1\n")
    folder = export_run(run, tmp_path / "export")
    assert folder.name == "bmc-b1000-nstep3-s1"
    for name in ("cell.json", "choice.json", "curve/curve.csv", "soak/soak.csv", "evaluation/summary.csv"):
        assert (folder / name).is_file(), name
    exported = read_exported(folder)
    assert exported.identity == ("bmc", 1000, 1, "nstep3")


def test_the_step_of_a_runner_killed_outright_is_recorded_as_killed_when_the_next_one_starts(tmp_path, monkeypatch):
    """A runner killed with SIGKILL (Slurm's KillWait, the OOM killer) writes no row; the next runner on the
    folder records its step as killed before it goes on."""
    spec, opts = RunSpec("bmc", 1000, 0), options(tmp_path)
    run = RunDir(tmp_path / spec.name)
    stack = lambda self, command, what, is_status, echo: (make_drive_run(run.root, 90_000, KEPT[:15]), FakeChild())[1]
    monkeypatch.setattr(grid_job.RunJob, "_start", stack)
    monkeypatch.setattr(grid_job, "trains_since", lambda *_: False)
    monkeypatch.setattr(grid_job, "record_step", lambda *_: None)  # as if it died before its step ended
    experiments.run_grid([spec], opts, parallel=1)
    monkeypatch.undo()
    monkeypatch.setattr(grid_job.RunJob, "_start", stack)
    monkeypatch.setattr(grid_job, "trains_since", lambda *_: False)
    experiments.run_grid([spec], opts, parallel=1)
    assert [(row["step"], row["outcome"]) for row in step_record.read_steps(run.root)] == [
        ("train", "killed"), ("resume", "failed")]  # the stand-in stack stops short again


def test_a_run_steps_through_to_done_and_a_rerun_resumes_where_it_stopped(tmp_path, monkeypatch):
    """The steps with every child a stand-in that leaves what the real one would: a stack stopped short is
    resumed, then the curve, the choice and the evaluation follow; a second run of the grid does nothing."""
    spec, opts = RunSpec("bmc", 1000, 0), options(tmp_path)
    run = RunDir(tmp_path / spec.name)
    calls = []

    def stand_in(self, command, what, is_status, echo):
        calls.append(what if what != "stack" else ("resume" if "--resume" in command else "train"))
        if what == "stack":
            reached = BUDGET if "--resume" in command else 90_000
            make_drive_run(run.root, reached, KEPT if reached == BUDGET else KEPT[:15])
        elif what == "curve":
            flag = dict(zip(command[5::2], command[6::2]))
            low, high = int(flag.get("--from-updates", 0)), int(flag.get("--to-updates", 10 ** 9))
            wanted = sorted(curve_wanted(KEPT, 1_000)) if flag["--sets"] == "test" else KEPT[-5:]
            old = list(csv.DictReader((run.curve / "curve.csv").open())) if (run.curve / "curve.csv").exists() else []
            write_curve(run, old + curve_rows([u for u in wanted if low <= u <= high], flag["--sets"]))
        elif what == "evaluate":
            fake_evaluation(run.evaluation, [100, 100], updates=json.loads((run.root / "choice.json").read_text())["updates"])
        return FakeChild()

    monkeypatch.setattr(grid_job.RunJob, "_start", stand_in)
    monkeypatch.setattr(grid_job, "trains_since", lambda *_: False)  # nothing beside the stand-in stack
    assert experiments.run_grid([spec], opts, parallel=1) == 1  # the first stack stops short: an error
    assert calls == ["train"]
    calls.clear()
    assert experiments.run_grid([spec], opts, parallel=1) == 0
    assert calls == ["resume", "curve", "curve", "curve", "evaluate"]  # the dense, the sparse, the choice's pass
    assert (tmp_path / "results" / "runs" / spec.name / "choice.json").is_file()
    steps = step_record.read_steps(tmp_path / "results" / "runs" / spec.name)  # exported with the run
    assert [(row["step"], row["outcome"]) for row in steps] == [
        ("train", "failed"), ("resume", "done"), ("curve", "done"), ("choose", "done"), ("evaluate", "done")]
    assert all(row["wall_s"] >= 0 and row["cpu"] and row["cores"] >= 1 for row in steps)
    calls.clear()
    assert experiments.run_grid([spec], opts, parallel=1) == 0 and calls == []
    started, start = [], grid_job.RunJob.start
    monkeypatch.setattr(grid_job.RunJob, "start", lambda self: (started.append(self.spec.name), start(self))[1])
    experiments.run_grid([RunSpec("vdbe", 1000, 0), spec], opts, parallel=1)
    assert started == [spec.name, "vdbe-b1000-s0"]  # a run already done goes first: counted done at once


def test_a_run_with_a_damaged_checkpoint_fails_alone(tmp_path, monkeypatch, capsys):
    opts = options(tmp_path)
    damaged = make_drive_run(tmp_path / "bmc-b1000-s0", BUDGET, KEPT)
    damaged.checkpoint.write_bytes(b"damaged")
    make_drive_run(tmp_path / "vdbe-b1000-s0", BUDGET, KEPT, curve_rows(sorted(curve_wanted(KEPT, 1_000)), "test")
                   + curve_rows(KEPT[-5:], "train"), strategy="vdbe")
    choose(RunDir(tmp_path / "vdbe-b1000-s0"))
    fake_evaluation(tmp_path / "vdbe-b1000-s0" / "evaluation", [100, 100], updates=30_000)
    monkeypatch.setattr(grid_job.RunJob, "_start", lambda *_: pytest.fail("nothing is to run"))
    assert experiments.run_grid([RunSpec("bmc", 1000, 0), RunSpec("vdbe", 1000, 0)], opts, parallel=1) == 1
    out = capsys.readouterr().out
    assert "cannot read the step count of" in out and (tmp_path / "results" / "runs" / "vdbe-b1000-s0").is_dir()


def finished_export(tmp_path: Path) -> Path:
    """The export of vdbe-b1000-s0 finished at 30,000 updates, in tmp_path/export/."""
    finished = make_drive_run(tmp_path / "elsewhere" / "vdbe-b1000-s0", BUDGET, KEPT,
                              curve_rows(sorted(curve_wanted(KEPT, 1_000)), "test") + curve_rows(KEPT[-5:], "train"),
                              strategy="vdbe")
    grid_cells.write_cell(finished, RunSpec("vdbe", 1000, 0), 30_000)
    choose(finished)
    fake_evaluation(finished.evaluation, [100, 100], updates=30_000)
    return export_run(finished, tmp_path / "export")


def test_a_run_exported_finished_is_done_where_its_folder_is_not(tmp_path, monkeypatch, capsys):
    """A fresh clone with the finished runs' exports committed goes on to the next run: an export of the run
    finished at this budget counts as done when its run folder holds nothing; at another budget, or once a
    run folder is started here, it does not."""
    exported = finished_export(tmp_path)
    argv = ["--strategies", "vdbe,bmc", "--seeds", "0", "--runs-dir", str(tmp_path / "runs"),
            "--export", str(exported.parent)]
    assert experiments.main([*argv, "--cells"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].endswith(f"next: done (exported to {exported})") and lines[1].endswith("next: train")
    assert experiments.main([*argv, "--updates", "20000", "--cells"]) == 0
    assert capsys.readouterr().out.splitlines()[0].endswith("next: train")  # finished at another budget
    monkeypatch.setattr(grid_job.RunJob, "_start", lambda *_, **__: pytest.fail("nothing is to run"))
    before = sorted((path, path.stat().st_mtime_ns) for path in exported.rglob("*"))
    assert experiments.run_grid([RunSpec("vdbe", 1000, 0)], experiments.parse_arguments(argv).options, 1) == 0
    assert "finished and exported to" in capsys.readouterr().out
    assert sorted((path, path.stat().st_mtime_ns) for path in exported.rglob("*")) == before  # left as it was
    make_drive_run(tmp_path / "runs" / "vdbe-b1000-s0", 90_000, KEPT[:15], strategy="vdbe")
    assert experiments.main([*argv, "--cells"]) == 0
    assert capsys.readouterr().out.splitlines()[0].endswith("next: resume")  # a run started here is its folder


def test_the_report_alone_says_which_runs_no_export_holds_finished(tmp_path, capsys):
    """The job after a scheduler's tasks: a run whose task did not finish is named with its next step; a
    run finished in its folder and exported is not, nor one exported elsewhere and merged."""
    exported = finished_export(tmp_path)
    make_drive_run(tmp_path / "runs" / "bmc-b1000-s0", 90_000, KEPT[:15])
    argv = ["--strategies", "vdbe,bmc,softmax", "--seeds", "0", "--runs-dir", str(tmp_path / "runs"), "--report-only"]
    experiments.main([*argv, "--export", str(exported.parent)])
    assert ("grid: 2 runs of 3 not finished and exported: cell 1 bmc-b1000-s0 (next: resume); cell 2 "
            "softmax-b1000-s0 (next: train)") in capsys.readouterr().out
    experiments.main([*argv, "--merge", str(exported.parent)])  # the run folder exists, the export is merged
    assert "grid: 2 runs of 3 not finished and exported: cell 1 bmc" in capsys.readouterr().out
    make_drive_run(tmp_path / "runs" / "vdbe-b1000-s0", 90_000, KEPT[:15], strategy="vdbe")  # trained on here
    experiments.main([*argv, "--export", str(exported.parent)])
    assert "2 runs of 3 not finished" in capsys.readouterr().out  # its export still holds it finished
    experiments.main([*argv, "--export", str(exported.parent), "--updates", "40000"])
    assert "3 runs of 3 not finished and exported: cell 0 vdbe-b1000-s0 (next: resume)" in capsys.readouterr().out


class FakeChild:
    process = type("Process", (), {"poll": staticmethod(lambda: 0)})()
    latest = ""

    def wait(self) -> int:
        return 0

    def interrupt(self) -> None:
        pass


class StackUntilInterrupted:
    """A stand-in for a run's stack (grid_job.Child) that trains until it is interrupted, as the real one does."""
    started: list = []
    running = threading.Event()
    latest = ""

    def __init__(self, *_):
        self.interrupted = threading.Event()
        self.process = self
        StackUntilInterrupted.started.append(self)
        StackUntilInterrupted.running.set()

    def poll(self) -> int | None:
        return 130 if self.interrupted.is_set() else None

    def wait(self) -> int:
        self.interrupted.wait(60)
        return 130

    def interrupt(self) -> None:
        self.interrupted.set()


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGHUP])
def test_a_signal_to_the_grid_interrupts_its_stacks_and_the_grid(tmp_path, monkeypatch, signum):
    """Ctrl-C, a kill and a closed terminal (SIGHUP) all stop the running stacks as an interruption does, and
    the grid says it was interrupted, so that the same command resumes."""
    monkeypatch.setattr(StackUntilInterrupted, "started", [])
    monkeypatch.setattr(StackUntilInterrupted, "running", threading.Event())
    monkeypatch.setattr(grid_job, "Child", StackUntilInterrupted)
    monkeypatch.setattr(grid_job, "trains_since", lambda *_: False)
    untouched = lambda *_: None  # not SIG_IGN, which a suite run under nohup passes on for SIGHUP
    before = signal.signal(signum, untouched)
    # the signal once the stack trains, however slowly a loaded machine starts the grid
    timer = threading.Thread(target=lambda: StackUntilInterrupted.running.wait(60) and os.kill(os.getpid(), signum),
                             daemon=True)
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            experiments.run_grid([RunSpec("bmc", 1000, 0)], options(tmp_path), parallel=1)
        stacks = StackUntilInterrupted.started
        assert len(stacks) == 1 and stacks[0].interrupted.is_set()
        assert signal.getsignal(signum) is untouched  # the grid's handler is given back
    finally:
        StackUntilInterrupted.running.set()  # the signaller ends at once if the grid never started a stack
        timer.join()
        signal.signal(signum, before)


def test_a_grid_with_no_finished_run_has_no_report_and_says_so(tmp_path, capsys):
    assert experiments.main(["--strategies", "bmc", "--seeds", "0", "--runs-dir", str(tmp_path), "--report-only"]) == 0
    assert "no run has finished yet" in capsys.readouterr().out
