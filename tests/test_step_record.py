"""A run's steps.csv (deploy/grid/step_record.py): one row per step, rows of older files kept, and the step of a
runner killed outright recorded as killed from the mark it left."""

from __future__ import annotations

import json
import os

from common.run_dir import RunDir
from deploy.grid import step_record


def rows(folder):
    return [(row["step"], row["wall_s"], row["outcome"]) for row in step_record.read_steps(folder)]


def test_a_damaged_steps_row_is_left_out(tmp_path):
    run = RunDir(tmp_path)
    step_record.record_step(run, "train", 0.0, "done")
    with (tmp_path / "steps.csv").open("a") as handle:
        handle.write("curve,x,ten,cpu,2,done\n")
    step_record.record_step(run, "curve", 1e9, "stopped")
    assert [(row["step"], row["outcome"]) for row in step_record.read_steps(tmp_path)] == [
        ("train", "done"), ("curve", "stopped")]
    assert step_record.read_steps(tmp_path / "nothing") == []


def test_a_steps_file_from_before_the_peak_column_takes_it_and_keeps_its_rows(tmp_path):
    (tmp_path / "steps.csv").write_text("step,started,wall_s,cpu,cores,outcome\ntrain,0,3600,AMD EPYC,2,done\n")
    step_record.record_step(RunDir(tmp_path), "curve", 0.0, "done", peak_mb=2100.4)
    step_record.record_step(RunDir(tmp_path), "choose", 0.0, "done")
    assert (tmp_path / "steps.csv").read_text().splitlines()[0] == ",".join(step_record.STEP_FIELDS)
    steps = step_record.read_steps(tmp_path)
    assert [(row["step"], row["wall_s"], row["peak_mb"]) for row in steps][0] == ("train", 3600.0, None)
    assert [row["peak_mb"] for row in steps[1:]] == [2100.0, None]


def test_a_step_whose_time_cannot_be_written_is_said_not_raised(tmp_path, capsys):
    step_record.record_step(RunDir(tmp_path / "gone" / "run"), "curve", 0.0, "done")
    assert "the curve step's time is not recorded" in capsys.readouterr().out


def test_a_step_that_ends_leaves_its_row_and_no_mark(tmp_path):
    run = RunDir(tmp_path)
    step_record.open_step(run, "train", 100.0)
    assert json.loads((tmp_path / step_record.OPEN_STEP_JSON).read_text())["step"] == "train"
    step_record.record_step(run, "train", 100.0, "stopped")
    assert not (tmp_path / step_record.OPEN_STEP_JSON).exists()
    assert step_record.close_killed_step(run) is None
    assert [(step, outcome) for step, _, outcome in rows(tmp_path)] == [("train", "stopped")]


def test_the_mark_of_a_killed_runner_becomes_a_killed_row_timed_to_its_logs_last_write(tmp_path):
    run = RunDir(tmp_path)
    step_record.record_step(run, "train", 0.0, "stopped")
    step_record.open_step(run, "resume", 1_000.0)  # then the runner is killed: no row, the mark stays
    run.logs.mkdir()
    for name, written in (("learner.log", 4_600.0), ("stack.log", 4_000.0)):
        (run.logs / name).write_text("...")
        os.utime(run.logs / name, (written, written))
    assert step_record.close_killed_step(run) == "resume"
    assert rows(tmp_path)[1] == ("resume", 3_600.0, step_record.KILLED)
    assert not (tmp_path / step_record.OPEN_STEP_JSON).exists()
    assert step_record.close_killed_step(run) is None and len(rows(tmp_path)) == 2  # counted once


def test_a_killed_step_without_logs_counts_no_time_and_a_damaged_mark_is_dropped(tmp_path, capsys):
    run = RunDir(tmp_path)
    step_record.open_step(run, "curve", 50.0)
    assert step_record.close_killed_step(run) == "curve" and rows(tmp_path) == [("curve", 0.0, "killed")]
    (tmp_path / step_record.OPEN_STEP_JSON).write_text('{"step": "curve", "started": "soon"}')
    assert step_record.close_killed_step(run) is None
    (tmp_path / step_record.OPEN_STEP_JSON).write_text('{"step": "curve", "started": NaN, "cpu": "x", "cores": 2}')
    assert step_record.close_killed_step(run) is None
    assert "unreadable" in capsys.readouterr().out and not (tmp_path / step_record.OPEN_STEP_JSON).exists()
    assert len(rows(tmp_path)) == 1
