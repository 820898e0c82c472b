"""The grid on a real Slurm (docs/slurm.md): a single-node cluster of Debian's slurm-wlm on this machine
(deploy/slurm/lab.py) runs a three-run smoke grid submitted by deploy/slurm/submit.py through
deploy/slurm/grid.sbatch. Every run must export and the report job, which depends on the array, must
build the report after every task ended. Two tasks are requeued while they train, one by `scontrol
requeue` (as a preemption or a lost node does), one by the batch script itself on the time limit's warning
(SIGUSR1): each must resume from its folder, from its checkpoint's updates, and not train again from zero.

Needs root (CI runs as root) and apt-get or an installed slurm-wlm and munge; elsewhere it skips with the
reason. The daemons, the jobs' processes and the lab's folder are removed at the end, also on failure.
"""

from __future__ import annotations

import csv
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from common.checkpoint import Checkpoint, CheckpointError
from common.run_dir import RunDir
from deploy.slurm.lab import SlurmLab, SlurmLabError, install, why_no_slurm

pytestmark = pytest.mark.lab  # run alone, after the rest (deploy/test.sh)

ROOT = Path(__file__).resolve().parents[1]
RUNS = ["bmc-b50-s0", "softmax-b50-s0", "vdbe-b50-s0"]  # the grid's cells 0, 1 and 2
# task -> how it is requeued while it trains: as by a preemption or the admin; by grid.sbatch itself at the
# time limit's warning (SIGUSR1 to the batch shell, as --signal=B:USR1@600 sends it)
REQUEUED = {1: ["scontrol", "requeue"], 2: ["scancel", "--batch", "--signal=USR1"]}
# 200 updates (two kept policies, every 100) at 2 env steps each; a small LSTM, episodes of a few steps
GRID = ["--strategies", "bmc,softmax,vdbe", "--buffers", "50", "--seeds", "0", "--updates", "200", "--trials", "1",
        "--preset", "smoke", "--pace.start_by", "steps", "--pace.env_steps_per_update", "2",
        "--network.lstm_units", "16", "--env.max_steps", "30", "--evaluation.max_steps", "10",
        "--evaluation.envs_per_worker", "16", "--env.render_scale", "2", "--progress-s", "10"]
TASK = ["--cpus", "2", "--mem", "1G", "--time", "0:20:00", "--partition", "lab"]
GRID_TIMEOUT_S = 600.0  # about 5 minutes alone on 2 cores; twice that beside other work


@pytest.fixture
def slurm(tmp_path):
    reason = why_no_slurm()
    if reason:
        pytest.skip(reason)
    try:
        install()
    except (SlurmLabError, subprocess.TimeoutExpired) as error:
        pytest.skip(f"cannot install slurm-wlm and munge here: {error}")
    lab = SlurmLab(tmp_path / "slurm", cpus=2 * len(RUNS), memory_mb=4096)  # the three tasks side by side
    try:
        lab.start()
        yield lab
    finally:
        lab.stop()


def wait(condition, what: str, timeout_s: float, lab: SlurmLab, runs: Path):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if value := condition():
            return value
        time.sleep(1.0)
    logs = "\n".join(f"--- {path.name}\n{path.read_text()[-3000:]}" for path in sorted((runs / "slurm").glob("*")))
    pytest.fail(f"no {what} after {timeout_s:.0f} s; queue: {lab.queued()}\n{logs}")


def checkpoint_updates(run: RunDir) -> int:
    try:
        return (Checkpoint.load(run.checkpoint).updates or 0) if run.checkpoint.is_file() else 0
    except CheckpointError:
        return 0  # being written


def requeue_while_training(lab: SlurmLab, array: str, runs: Path) -> dict[int, int]:
    """Requeues the REQUEUED tasks once their runs have checkpointed and before they end training; by
    task, the updates of the checkpoint it finds when it starts again."""
    folders = {number: RunDir(runs / RUNS[number]) for number in REQUEUED}
    wait(lambda: all(checkpoint_updates(run) >= 50 for run in folders.values()), "checkpoints of the runs to requeue",
         GRID_TIMEOUT_S, lab, runs)
    for number, command in REQUEUED.items():
        lab.run(*command, f"{array}_{number}")
    wait(lambda: all(lab.job(f"{array}_{number}")["JobState"] == "PENDING" for number in REQUEUED),
         "requeued tasks pending again", 120, lab, runs)
    resumed_from = {number: checkpoint_updates(run) for number, run in folders.items()}
    for number in REQUEUED:  # slurmctld holds a requeued job back two minutes (its BeginTime): start it now
        lab.run("scontrol", "update", f"JobId={array}_{number}", "StartTime=now")
    return resumed_from


@pytest.mark.timeout(GRID_TIMEOUT_S + 300)  # the install, and the daemons' start and stop
def test_a_smoke_grid_runs_as_an_array_resumes_requeued_tasks_and_reports_after_them(slurm, tmp_path):
    started = time.monotonic()
    runs = tmp_path / "runs"
    submitted = subprocess.run([sys.executable, str(ROOT / "deploy" / "slurm" / "submit.py"), "--runs-dir", str(runs),
                                *TASK, *GRID], capture_output=True, text=True, env=slurm.environment, timeout=120)
    assert submitted.returncode == 0, submitted.stderr
    array, report = re.search(r"array job (\d+); the report as job (\d+)", submitted.stdout).groups()
    resumed_from = requeue_while_training(slurm, array, runs)
    wait(lambda: not slurm.queued(), "end of the grid and its report", GRID_TIMEOUT_S, slurm, runs)

    tasks = [slurm.job(f"{array}_{number}") for number in range(len(RUNS))]
    merge = slurm.job(report)
    logs = {path.name: path.read_text() for path in (runs / "slurm").glob("*.out")}
    assert [job["JobState"] for job in tasks] == ["COMPLETED"] * 3, logs
    assert merge["JobState"] == "COMPLETED", logs
    assert merge["StartTime"] >= max(job["EndTime"] for job in tasks)  # ISO times: ordered as text
    for name in RUNS:
        export = runs / "results" / "runs" / name
        assert (export / "evaluation" / "summary.csv").is_file() and (export / "choice.json").is_file(), name
    grid_md = (runs / "results" / "grid.md").read_text()
    assert all(name in grid_md for name in RUNS)
    assert "not finished and exported" not in logs[f"d3rqn-grid-report-{report}.out"]
    assert [job["Restarts"] for job in tasks] == ["0", "1", "1"]
    for number, updates in resumed_from.items():
        assert_resumed(RunDir(runs / RUNS[number]), updates, logs[f"d3rqn-grid-{array}_{number}.out"])
    print(f"the grid on Slurm took {time.monotonic() - started:.0f} s; tasks 1 and 2 resumed from "
          f"{resumed_from[1]} and {resumed_from[2]} updates")


def assert_resumed(run: RunDir, updates: int, log: str) -> None:
    """The task ran twice, and its second start resumed the run from the checkpoint it found."""
    assert "start 1 after requeues" in log
    with (run.root / "steps.csv").open() as handle:
        steps = [(row["step"], row["outcome"]) for row in csv.DictReader(handle)]
    # stopped: its processes checkpointed within KillWait; killed: Slurm's SIGKILL came first, and the next
    # start recorded the step from its mark (deploy/grid/step_record.py). Either way it must resume.
    stack_log = run.log("stack").read_text(errors="replace")[-3000:] if run.log("stack").is_file() else ""
    assert steps[0] in {("train", "stopped"), ("train", "killed")} and steps[1] == ("resume", "done"), (
        steps, log[-3000:], stack_log)
    assert [step for step, _ in steps].count("train") == 1 and not run.abandoned("").exists()  # no fresh start
    assert updates >= 50 and f": {updates} updates," in run.log("learner").read_text()
