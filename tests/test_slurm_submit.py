"""deploy/slurm/submit.py without a cluster: the array and report commands it builds, where each setting
comes from, what it refuses, and the dependency it submits, against a stand-in sbatch on PATH. The real
cluster is tests/test_slurm_grid.py."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from deploy.slurm import submit

GRID = ["--strategies", "bmc,softmax", "--seeds", "0,1,2"]  # 6 runs


def commands(argv: list[str], environ: dict | None = None) -> submit.Submission:
    args, grid_flags = submit.build_parser().parse_known_args(argv)
    return submit.submission(args, grid_flags, environ or {})


def options(command: list[str]) -> dict[str, str]:
    return dict(word[2:].split("=", 1) for word in command if word.startswith("--") and "=" in word)


def test_one_task_per_run_with_the_scripts_settings_and_the_same_grid_flags_for_the_report(tmp_path):
    plan = commands(["--runs-dir", str(tmp_path / "grid"), *GRID])
    array, report = options(plan.array), options(plan.report)
    assert array["array"] == "0-5" and plan.runs == 6
    assert (array["cpus-per-task"], array["mem"], array["time"]) == ("2", "4G", "6:00:00")  # grid.sbatch's
    assert "partition" not in array  # the cluster's default partition
    assert report["job-name"] == "d3rqn-grid-report" and "--no-requeue" in plan.report and "array" not in report
    tail = [str(submit.SCRIPT), *GRID, "--runs-dir", str(tmp_path / "grid")]
    assert plan.array[-len(tail):] == tail and plan.report[-len(tail):] == tail
    assert array["output"] == f"{tmp_path}/grid/slurm/%x-%A_%a.out"


def test_a_setting_comes_from_its_flag_else_its_variable_else_the_script(tmp_path):
    environ = {"D3RQN_SLURM_MEM": "6G", "D3RQN_SLURM_PARTITION": "cpu", "D3RQN_SLURM_TIME": "2:00:00"}
    array = options(commands(["--runs-dir", str(tmp_path), "--time", "9:00:00", "--max-running", "3", *GRID],
                             environ).array)
    assert (array["mem"], array["partition"], array["time"], array["cpus-per-task"]) == ("6G", "cpu", "9:00:00", "2")
    assert array["array"] == "0-5%3"


@pytest.mark.parametrize("argv, message", [
    (["--cell", "2"], "--cell: set by the submission"),
    (["--parallel=2"], "--parallel=2: set by the submission"),
    (["--seeds", "0,0"], "the grid's flags: --seeds"),
    (["--max-running", "0"], "--max-running: must be > 0"),
])
def test_what_the_submission_sets_or_the_grid_refuses_is_an_error(tmp_path, argv, message):
    with pytest.raises(submit.SubmitError, match=message):
        commands(["--runs-dir", str(tmp_path), *GRID, *argv])


def test_the_report_is_submitted_after_the_array_with_its_job_id(tmp_path, monkeypatch, capsys):
    calls = tmp_path / "calls"
    fake = tmp_path / "bin" / "sbatch"
    fake.parent.mkdir()
    # the array is job 41, the report 42; --parsable prints "id;cluster" on a federation
    fake.write_text(f'#!/bin/sh\necho "$*" >> {calls}\n'
                    f'if [ $(wc -l < {calls}) = 1 ]; then echo 41; else echo "42;lab"; fi\n')
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", f"{fake.parent}{os.pathsep}{os.environ['PATH']}")
    assert submit.main(["--runs-dir", str(tmp_path / "grid"), *GRID]) == 0
    array, report = calls.read_text().splitlines()
    assert "--array=0-5" in array and "--dependency=afterany:41" in report.split()
    assert "array job 41; the report as job 42" in capsys.readouterr().out
    assert (tmp_path / "grid" / "slurm").is_dir()  # sbatch writes no log into a missing folder


def test_a_refusing_sbatch_is_said(tmp_path, monkeypatch, capsys):
    fake = tmp_path / "sbatch"
    fake.write_text('#!/bin/sh\necho "sbatch: error: invalid partition specified: gpu" >&2\nexit 1\n')
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", f"{tmp_path}{os.pathsep}{os.environ['PATH']}")
    assert submit.main(["--runs-dir", str(tmp_path / "grid"), "--partition", "gpu", *GRID]) == 2
    assert "sbatch refused the job (1): sbatch: error: invalid partition" in capsys.readouterr().err


def test_without_sbatch_the_submission_says_so(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("PATH", str(tmp_path))
    assert submit.main(["--runs-dir", str(tmp_path / "grid"), *GRID]) == 2
    assert "no sbatch here" in capsys.readouterr().err
