"""A log on a full disk ends no process: the config printed at start, log lines and prints are dropped while the
disk refuses them, counted, and said once space returns; a role that dies of a full disk all the same exits with
DISK_FULL_EXIT, which the stack answers by waiting for space."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from common.disk_space import DISK_FULL_EXIT
from common.log_streams import DiskTolerantStream
from full_disk import FULL_DEVICE

ROOT = Path(__file__).resolve().parents[1]

ROLE = textwrap.dedent("""
    import argparse, logging
    from common.shell import parse_service_args, run_main
    from common.logs import setup_logging

    def main():
        parse_service_args(argparse.ArgumentParser(prog="role"), ["--preset", "smoke"])  # prints the config
        setup_logging("role")
        for index in range(50):
            logging.getLogger("role").info("line %d", index)
        print("a print")
        {end}

    run_main(main)
""")


def run_role(end: str, log) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", ROLE.format(end=end)], cwd=ROOT, stdout=log, stderr=log,
                          env={**os.environ, "PYTHONPATH": str(ROOT)}, timeout=120)


def test_a_role_whose_log_is_on_a_full_disk_goes_on():
    with open(FULL_DEVICE, "wb") as full:
        assert run_role("return 0", full).returncode == 0


def test_a_role_that_dies_of_a_full_disk_exits_with_its_own_code(tmp_path):
    end = "raise OSError(28, 'No space left on device')"
    with open(tmp_path / "role.log", "wb") as log:
        done = run_role(end, log)
    assert done.returncode == DISK_FULL_EXIT
    assert "stopping: the disk is full" in (tmp_path / "role.log").read_text()


class Stream:
    def __init__(self, fd: int) -> None:
        self.fd = fd

    def fileno(self) -> int:
        return self.fd

    def flush(self) -> None:
        pass


def test_writes_a_full_disk_refuses_are_counted_and_said_once_space_returns(tmp_path):
    fd = os.open(FULL_DEVICE, os.O_WRONLY)
    try:
        stream = DiskTolerantStream(Stream(fd))
        for _ in range(3):
            assert stream.write("lost\n") == 5
        assert stream.dropped == 3
        log = os.open(tmp_path / "log", os.O_WRONLY | os.O_CREAT)
        os.dup2(log, fd)  # space returns
        os.close(log)
        stream.write("kept\n")
    finally:
        os.close(fd)
    assert (tmp_path / "log").read_text() == "\n[3 writes to this log lost: the disk was full]\nkept\n"
    assert stream.dropped == 0 and stream.dropped_total == 3


def test_any_other_write_error_is_raised():
    reader, writer = os.pipe()
    os.close(reader)
    try:
        with pytest.raises(BrokenPipeError):
            DiskTolerantStream(Stream(writer)).write("nobody reads\n")
    finally:
        os.close(writer)


def test_the_stacks_console_on_a_full_disk_drops_the_line_and_the_run_goes_on(monkeypatch):
    import threading

    from deploy.launcher.console import Console
    full = open(FULL_DEVICE, "w")
    monkeypatch.setattr(sys, "stdout", full)
    try:
        console = Console(threading.Event())
        console.say("a line the disk refuses")
        assert not console.stop.is_set() and not console.gone
    finally:
        monkeypatch.undo()
        with contextlib.suppress(OSError):  # the line is still in its buffer
            full.close()
