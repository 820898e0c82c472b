"""Starting and stopping real processes in tests: free ports, logs to files, nothing left running."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import zenoh

from common.config import TransportConfig
from common.transport import free_port, loopback_endpoint, open_session  # ports re-exported: the tests take them here

STOP_TIMEOUT_S = 30.0
# a router process just started imports torch before it listens: on a loaded 2-core machine that took longer
# than the client's default 10 s of connect retries
ROUTER_START_S = 60.0


def from_a_terminal() -> None:
    """A child's preexec_fn: SIGHUP as a terminal leaves it, where the suite itself runs under nohup (which
    passes it on ignored, and a process of a run keeps it so)."""
    signal.signal(signal.SIGHUP, signal.SIG_DFL)


def start(args: list[str], log_path: Path, cwd: Path | None = None) -> subprocess.Popen:
    """`python <args>` with stdout and stderr in log_path, started as from a terminal."""
    with open(log_path, "wb") as log:
        return subprocess.Popen([sys.executable, *args], stdout=log, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, cwd=cwd, preexec_fn=from_a_terminal)


def router_client(endpoint: str) -> zenoh.Session:
    """A client session to a router process that may still be starting (close it, or use it with `with`)."""
    return open_session(TransportConfig(mode="client", connect=[endpoint], connect_timeout_s=ROUTER_START_S))


def stop(*processes: subprocess.Popen) -> None:
    """SIGINT to all, then wait; kill whatever does not stop in time."""
    for process in processes:
        if process.poll() is None:
            process.send_signal(signal.SIGINT)
    for process in processes:
        try:
            process.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def alive(pid: int) -> bool:
    """Whether the process runs: a zombie has exited, only its reaping is left."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().split(") ", 1)[1][0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


def wait_for(condition, what: str, timeout_s: float, logs: list[Path] = ()) -> None:
    """Polls condition() until true; on timeout fails with the tail of the given logs."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return
        time.sleep(0.1)
    tails = "\n".join(f"--- {path.name}\n{path.read_text(errors='replace')[-2000:]}" for path in logs if path.exists())
    raise AssertionError(f"timed out after {timeout_s:.0f}s waiting for {what}\n{tails}")


def children(pid: int) -> dict[int, str]:
    """Direct children of pid with their command lines (from /proc)."""
    found = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            parent = int(stat.rsplit(")", 1)[1].split()[1])
            if parent == pid:
                found[int(entry.name)] = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
        except (OSError, ValueError, IndexError):
            continue
    return found


def kill_tree(process: subprocess.Popen) -> None:
    """SIGKILL to a process that did not stop and to its children (a stack's roles)."""
    leftovers = children(process.pid)
    process.kill()
    process.wait()
    for pid in leftovers:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
