"""The run folder: every path of a run from one place, the checkpoint a path names, the status file."""

import pytest

from common.config_values import load_config
from common.run_dir import RunDir, RunStatus, StatusError, find_checkpoint


def test_a_run_folder_comes_from_the_config_and_holds_every_path(tmp_path):
    run = RunDir.of(load_config("smoke", overrides={"run.runs_dir": str(tmp_path), "run.name": "bmc"}))
    assert run.root == tmp_path / "bmc"
    paths = [run.config, run.log("learner"), run.checkpoint, run.replay_counters, run.replay_snapshot,
             run.wire_log, run.evaluation, run.status, run.summary, run.abandoned("20250101-000000")]
    assert all(path.is_relative_to(run.root) for path in paths)
    assert len(set(paths)) == len(paths)
    assert run.log("learner").parent == run.logs and run.checkpoint.parent == run.checkpoints


def test_the_run_of_a_checkpoint_is_the_folder_above_its_checkpoints_folder(tmp_path):
    run = RunDir(tmp_path / "bmc")
    assert RunDir.of_checkpoint(run.checkpoint) == run
    assert RunDir.of_checkpoint(tmp_path / "saved" / "early.pt") == RunDir(tmp_path / "saved")


def test_a_checkpoint_is_found_from_its_file_its_folder_or_its_run(tmp_path):
    run = RunDir(tmp_path / "bmc")
    assert find_checkpoint(run.root) is None and find_checkpoint(tmp_path / "missing") is None
    run.checkpoints.mkdir(parents=True)
    run.checkpoint.write_bytes(b"x")
    assert find_checkpoint(run.root) == find_checkpoint(run.checkpoints) == find_checkpoint(run.checkpoint) \
        == run.checkpoint


def test_the_wire_logs_of_a_run_are_its_numbered_segments_in_order(tmp_path):
    run = RunDir(tmp_path)
    assert run.wire_log_segments() == []
    second = run.wire_log.with_name(run.wire_log.stem + "-2" + run.wire_log.suffix)
    for path in (run.wire_log, second):
        path.write_bytes(b"")
    assert run.wire_log_segments() == [run.wire_log, second]


def test_a_status_reads_back_as_written_and_leaves_no_temporary_file(tmp_path):
    status = RunStatus(phase="training", env_steps=1200, total_env_steps=60000, updates=30, episodes=7,
                       mean_return=3.25, eta_s=812.5, elapsed_s=61.0, restarts={"actor-0": 1},
                       pids={"learner": 4242}, time=1.7e9)
    path = tmp_path / "status.json"
    status.write(path)
    assert RunStatus.read(path) == status
    assert [item.name for item in tmp_path.iterdir()] == ["status.json"]
    RunStatus(phase="stopped").write(path)  # over the old one
    assert RunStatus.read(path) == RunStatus(phase="stopped")


@pytest.mark.parametrize("text, message", [
    ("{\"phase\": \"training\", \"env_st", "cannot read the status file"),  # cut short
    ("[1, 2]", "is not a run status file"),
    ("{\"env_steps\": 5}", "is not a run status file"),  # no phase
    ("{\"phase\": \"training\", \"colour\": \"red\"}", "is not a run status file"),
    ("{\"phase\": \"training\", \"env_steps\": \"many\", \"pids\": {\"learner\": 1.5}}", "env_steps, pids of the wrong type"),
    ("{\"phase\": \"training\", \"updates\": true}", "updates of the wrong type"),
])
def test_a_damaged_status_file_is_one_clear_error(tmp_path, text, message):
    path = tmp_path / "status.json"
    path.write_text(text)
    with pytest.raises(StatusError, match=message):
        RunStatus.read(path)


def test_a_missing_status_file_is_a_status_error(tmp_path):
    with pytest.raises(StatusError, match="cannot read the status file"):
        RunStatus.read(tmp_path / "status.json")

