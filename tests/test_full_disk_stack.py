"""The stack on a full disk: free space on the live line and in status.json, a warning while it is below what the
next checkpoint and snapshot need, a process that ended for a full disk started again only once there is room,
and a config it cannot write a clear line, not a truncated file."""

from __future__ import annotations

import threading
import time

import pytest

from common.config_values import load_config
from common.disk_space import DISK_FULL_EXIT, MEGABYTE
from common.run_dir import RunDir, RunStatus
from deploy.launcher import stack as stack_module
from deploy.launcher.console import Console
from deploy.launcher.disk_watch import START_MIN_BYTES, DiskWatch
from deploy.launcher.stack import Stack
from deploy.launcher.stack_monitor import StackMonitor


class Ended:
    """A process that has exited with `code`."""

    def __init__(self, code: int) -> None:
        self.code, self.pid = code, 0

    def poll(self) -> int:
        return self.code


class Running(Ended):
    def __init__(self) -> None:
        super().__init__(0)

    def poll(self) -> None:
        return None


def test_the_watch_warns_once_while_free_space_is_below_the_next_checkpoint_and_snapshot(tmp_path):
    run = RunDir(tmp_path)
    run.checkpoints.mkdir()
    run.checkpoint.write_bytes(b"c" * 3000)
    run.replay_snapshot.mkdir(parents=True)
    (run.replay_snapshot / "segment-00000000.bin").write_bytes(b"s" * 500)
    (run.replay_snapshot / "segment-00000001.bin").write_bytes(b"s" * 700)
    (run.replay_snapshot / "manifest.msgpack").write_bytes(b"m" * 100)
    free, said = [10_000], []
    watch = DiskWatch(run, said.append, free_space=lambda: free[0])
    assert watch.needed() == 3000 + 700 + 100
    for free[0] in (10_000, 3_000, 2_000, 1_000, 5_000, 4_000):
        assert watch.look() == free[0]
    assert len(said) == 2 and "less than the next checkpoint and snapshot need" in said[0], said
    assert "room again" in said[1]


def test_the_line_and_the_status_file_show_the_free_space(tmp_path):
    monitor = StackMonitor(1000)
    assert monitor.line(2, 1536 * MEGABYTE).endswith("restarts 2 | disk free 1,536.0 MB")
    monitor.status("training", {}, {}, 42).write(tmp_path / "status.json")
    assert RunStatus.read(tmp_path / "status.json").disk_free_bytes == 42


def test_a_process_ended_by_a_full_disk_starts_again_only_once_there_is_room(tmp_path, monkeypatch):
    monkeypatch.setattr(stack_module, "RESTART_BACKOFF_S", 0.05)
    monkeypatch.setattr(stack_module, "SPACE_POLL_S", 0.05)
    config = load_config("smoke", overrides={"run.runs_dir": str(tmp_path), "recorder.enabled": True})
    run = RunDir.of(config)
    stop, said = threading.Event(), []
    stack = Stack(config, run, "tcp/127.0.0.1:1", 1, False, console=Console(threading.Event()))
    free = [0]
    stack.disk = DiskWatch(run, said.append, free_space=lambda: free[0])
    started = []

    def start(role, first: bool = False) -> None:
        started.append(role.name)
        role.process, role.started = Running(), time.monotonic()

    monkeypatch.setattr(stack, "_start", start)
    for role in stack.roles.values():
        role.process = Running()
    stack.roles["recorder"].process = Ended(DISK_FULL_EXIT)
    watching = threading.Thread(target=stack.watch, args=(stop, StackMonitor()), daemon=True)
    watching.start()
    try:
        time.sleep(1.0)  # twenty backoffs: none starts it into a full disk
        assert started == [] and stack.roles["recorder"].waits_for_space
        free[0] = START_MIN_BYTES  # space returns
        deadline = time.monotonic() + 5.0
        while not started and time.monotonic() < deadline:
            time.sleep(0.05)
        assert started == ["recorder"] and stack.restarts["recorder"] == 1
    finally:
        stop.set()
        watching.join(5.0)


def test_a_config_the_disk_refuses_is_a_line_and_exit_code_1_leaving_the_old_one(tmp_path, monkeypatch, capsys):
    run = tmp_path / "r"
    run.mkdir()
    (run / "config.toml").write_text("# the run's config\n")

    def refuse(path, text):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(stack_module, "write_text_atomically", refuse)
    code = stack_module.main(["--preset", "smoke", "--run.runs_dir", str(tmp_path), "--run.name", "r"])
    assert code == 1 and "cannot write" in capsys.readouterr().err
    assert (run / "config.toml").read_text() == "# the run's config\n"


@pytest.mark.parametrize("code", [1, DISK_FULL_EXIT])
def test_only_a_full_disk_exit_waits_for_room(tmp_path, code):
    config = load_config("smoke", overrides={"run.runs_dir": str(tmp_path)})
    stack = Stack(config, RunDir.of(config), "tcp/127.0.0.1:1", 1, False, console=Console(threading.Event()))
    stack.disk = DiskWatch(stack.run, lambda line: None, free_space=lambda: 0)
    stack._died(stack.roles["learner"], code, time.monotonic())
    assert stack.roles["learner"].waits_for_space == (code == DISK_FULL_EXIT)
