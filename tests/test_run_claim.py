"""One stack per run folder (deploy/launcher/run_claim.py), and a stack that stops cleanly once nobody reads its
output (deploy/launcher/console.py)."""

import io
import json
import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from common.run_dir import RunDir
from deploy.launcher.console import Console
from deploy.launcher.run_claim import RunClaimError, claim_run, lingering_pids
from tests.processes import wait_for


def run_folder(tmp_path) -> RunDir:
    run = RunDir(tmp_path / "runs" / "r1")
    run.root.mkdir(parents=True)
    run.config.write_text("")
    return run


def test_a_second_claim_on_a_run_folder_is_refused_until_the_first_ends(tmp_path):
    run = run_folder(tmp_path)
    first = claim_run(run)
    with pytest.raises(RunClaimError, match="is in use by another stack"):
        claim_run(run)
    first.close()  # the kernel drops the lock of a stack that ends, however it ends
    claim_run(run).close()
    run.stack_lock.unlink()
    run.stack_lock.mkdir()  # something else in the lock file's place: a clear error, not a traceback
    with pytest.raises(RunClaimError, match="cannot open the run's lock file"):
        claim_run(run)


def test_a_run_whose_earlier_stack_left_processes_alive_waits_for_them(tmp_path):
    run = run_folder(tmp_path)
    # a process of the earlier stack: started elsewhere, naming the run's config by a relative path
    role = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)", "--config", "r1/config.toml"],
                            cwd=run.root.parent)
    try:
        wait_for(lambda: Path(f"/proc/{role.pid}/cmdline").read_bytes(), "the process's command line", 10)
        status = {"phase": "training", "pids": {"learner": role.pid, "replay": os.getpid()}}  # the test: another config
        run.status.write_text(json.dumps(status))
        assert lingering_pids(run) == [role.pid]
        with pytest.raises(RunClaimError, match=f"still alive after 0 s \\(pids {role.pid}\\)"):
            claim_run(run, wait_s=0.2)
        threading.Timer(0.5, role.kill).start()  # it stops while the next stack waits
        claim_run(run, wait_s=30).close()
    finally:
        role.kill()
        role.wait()
    assert lingering_pids(run) == []
    run.status.write_text("{not json")  # a damaged status names nobody to wait for
    assert lingering_pids(run) == []


def unread_stream():
    """A text stream on a pipe whose reading end is closed."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    return io.TextIOWrapper(io.FileIO(write_end, "w"), write_through=True)


def test_the_console_stops_the_run_once_its_reader_is_gone_and_says_nothing_more(monkeypatch):
    unread = unread_stream()
    monkeypatch.setattr(sys, "stdout", unread)  # in the test: pytest sets its own sys.stdout after the fixtures
    stop = threading.Event()
    console = Console(stop)
    console.say("a line nobody reads")  # no BrokenPipeError escapes
    assert stop.is_set() and console.gone == {"stdout"}
    console.say("another")  # silenced: the stream now points at /dev/null
    unread.write("left in the buffer\n")
    unread.flush()


def test_the_console_notices_a_gone_reader_without_writing(monkeypatch):
    monkeypatch.setattr(sys, "stdout", unread_stream())
    stop = threading.Event()
    console = Console(stop)
    assert not console.check() and stop.is_set() and console.gone == {"stdout"}


def test_the_console_leaves_a_read_stream_alone(monkeypatch, tmp_path):
    read_end, write_end = os.pipe()
    try:
        monkeypatch.setattr(sys, "stdout", io.TextIOWrapper(io.FileIO(write_end, "w", closefd=False),
                                                            write_through=True))
        console = Console(threading.Event())
        assert console.check()
        console.say("read")
        assert os.read(read_end, 100) == b"read\n" and not console.stop.is_set()
    finally:
        os.close(read_end)
        os.close(write_end)


def test_a_file_system_without_locks_is_said_and_the_run_goes_on(tmp_path, monkeypatch, caplog):
    run = run_folder(tmp_path)

    def no_locks(handle, operation):
        raise OSError(37, "No locks available")

    monkeypatch.setattr("deploy.launcher.run_claim.fcntl.flock", no_locks)
    claim_run(run).close()
    assert "cannot lock" in caplog.text and "No locks available" in caplog.text


def test_a_console_without_stdout_says_nothing_and_goes_on(monkeypatch):
    monkeypatch.setattr(sys, "stdout", None)  # Python's sys.stdout when fd 1 was closed at its start
    console = Console(threading.Event())
    assert console.check()
    console.say("nowhere")
    assert not console.stop.is_set()
