"""The main job (deploy/run.sh -> deploy/main_job.py): the stack, then the grid's steps, ending with the chosen
policy in runs/<run>/policy.pt and its evaluation; every child a stand-in that leaves what the real one would."""

from __future__ import annotations

import contextlib
import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from common.run_dir import RunDir
from deploy import main_job
from deploy.grid.grid_cells import curve_wanted, read_choice
from tests.grid_runs import fake_evaluation
from tests.processes import from_a_terminal
from tests.test_grid_runner import BUDGET, KEPT, curve_rows, make_drive_run, write_curve

ROOT = Path(__file__).resolve().parents[1]


def stand_in(run: RunDir, calls: list[str], reached: int = BUDGET):
    def call(command: list[str]) -> None:
        if command[1].endswith("stack.py"):
            calls.append("stack")
            make_drive_run(run.root, reached, KEPT if reached == BUDGET else KEPT[:5])
            for kept in KEPT:
                run.policy(kept).write_bytes(f"weights {kept}".encode())
        elif "--curve" in command:
            sets = command[command.index("--sets") + 1]
            calls.append(f"curve {sets}")
            old = list(csv.DictReader(run.curve.joinpath("curve.csv").open())) if (run.curve / "curve.csv").exists() else []
            new = sorted(curve_wanted(KEPT, 1_000)) if sets == "test" else KEPT[-5:]
            write_curve(run, old + [row for row in curve_rows(new, sets) if str(row["updates"]) not in
                                    {r["updates"] for r in old if r["start_set"] == sets}])
        else:
            calls.append("evaluate")
            fake_evaluation(run.evaluation, [100, 50], updates=read_choice(run)["updates"])
    return call


def test_the_main_job_trains_then_reads_chooses_evaluates_and_ships_the_policy(tmp_path, monkeypatch, capsys):
    run, calls = RunDir(tmp_path / "job"), []
    monkeypatch.setattr(main_job, "call", stand_in(run, calls))
    assert main_job.main(["--run.runs_dir", str(tmp_path), "--run.name", "job"]) == 0
    assert calls == ["stack", "curve test", "curve test", "curve train", "evaluate"]
    chosen = read_choice(run)["updates"]
    assert (run.root / "policy.pt").read_bytes() == f"weights {chosen}".encode()
    out = capsys.readouterr().out
    assert f"{run.root / 'policy.pt'}" in out and "evaluation/summary.md" in out
    calls.clear()
    assert main_job.main(["--run.runs_dir", str(tmp_path), "--run.name", "job"]) == 0  # done: nothing again
    assert calls == []


def test_a_main_job_stopped_in_training_says_how_to_go_on(tmp_path, monkeypatch):
    run, calls = RunDir(tmp_path / "job"), []
    monkeypatch.setattr(main_job, "call", stand_in(run, calls, reached=60_000))
    with pytest.raises(SystemExit, match="--resume"):
        main_job.main(["--run.runs_dir", str(tmp_path), "--run.name", "job"])
    assert calls == ["stack"]


def test_a_config_that_keeps_no_policy_gets_one_kept_every_1000_updates(tmp_path, monkeypatch, capsys):
    commands = []
    monkeypatch.setattr(main_job, "call", lambda command: commands.append(command) or None)
    monkeypatch.setattr(main_job, "read_run", lambda *args: None)
    monkeypatch.setattr(main_job.shutil, "copy2", lambda *args: None)
    monkeypatch.setattr(main_job, "read_choice", lambda run: {"updates": 1000})
    monkeypatch.setattr(main_job, "greedy_headline", lambda folder: "")
    main_job.main(["--preset", "paper", "--run.runs_dir", str(tmp_path), "--run.name", "p"])
    assert commands[0][-2:] == ["--learner.keep_every", "1000"] and "keeping a policy" in capsys.readouterr().out


CHECKPOINTING_CHILD = """
import pathlib, signal, sys, time
folder = pathlib.Path(sys.argv[1])
def checkpoint(*_):
    time.sleep(0.5)  # the parent must wait through this
    (folder / "checkpointed").write_text("yes")
    sys.exit(0)
signal.signal(signal.SIGINT, checkpoint)
(folder / "ready").write_text("yes")
while True:
    time.sleep(0.05)
"""


@pytest.mark.parametrize("whom, signum", [("terminal", signal.SIGINT), ("job alone", signal.SIGINT),
                                          ("job alone", signal.SIGTERM), ("job alone", signal.SIGHUP)])
def test_a_stop_waits_for_the_child_to_checkpoint_and_exits_130_in_one_line(tmp_path, whom, signum):
    """A terminal's Ctrl-C reaches the job and its child; a signal to the job alone (a service manager's
    SIGTERM) must be handed on. The job stands in by one call of the real child; it starts with SIGINT ignored,
    as a job started in the background of a script does (and as pytest itself may run)."""
    job = subprocess.Popen([sys.executable, "-c", "import sys; from deploy import main_job; sys.exit(main_job."
                            f"stoppable(lambda: main_job.call([sys.executable, '-c', {CHECKPOINTING_CHILD!r}, "
                            f"{str(tmp_path)!r}])))"], stderr=subprocess.PIPE, text=True, start_new_session=True, cwd=ROOT,
                           preexec_fn=lambda: from_a_terminal() or signal.signal(signal.SIGINT, signal.SIG_IGN))
    try:
        deadline = time.monotonic() + 30
        while not (tmp_path / "ready").exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        if whom == "terminal":
            os.killpg(job.pid, signum)
        else:
            job.send_signal(signum)
        _, err = job.communicate(timeout=30)
    finally:
        with contextlib.suppress(ProcessLookupError):  # the job's group: a child left behind by a broken job too
            os.killpg(job.pid, signal.SIGKILL)
        job.wait()
    assert job.returncode == 130 and (tmp_path / "checkpointed").exists()
    assert "Traceback" not in err and err.strip().splitlines() == [main_job.STOPPED]
