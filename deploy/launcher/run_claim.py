"""One stack per run folder. Two stacks on one run (the same command twice, or a grid restarted while an
earlier stack's processes still stop) would train two learners on one checkpoint and write both into the
folder. The stack that runs a run holds an exclusive lock on it, which the kernel drops when that stack
dies however it dies; and a stack waits for processes of an earlier stack of the run (the pids of its
status file, started with the run's config) to stop, and does not start while they live.
"""

from __future__ import annotations

import fcntl
import logging
import os
import time
from pathlib import Path
from typing import IO

from common.run_dir import RunDir, RunStatus, StatusError

log = logging.getLogger("stack")
# an earlier stack's roles stop within a second of its end, the learner after its checkpoint
LINGER_WAIT_S = 60.0
LINGER_POLL_S = 0.5


class RunClaimError(Exception):
    """The run folder is in use, or its lock file cannot be opened; the message says why and what to do."""


def claim_run(run: RunDir, wait_s: float = LINGER_WAIT_S) -> IO:
    """The open, locked lock file: keep it open while the stack runs. RunClaimError if another stack runs the run,
    or if processes of an earlier one are still alive after wait_s."""
    try:
        handle = open(run.stack_lock, "a+")
    except OSError as error:  # a read-only folder, or something else in the lock file's place
        raise RunClaimError(f"cannot open the run's lock file {run.stack_lock}: {error}") from None
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.close()
        raise RunClaimError(f"run folder {run.root} is in use by another stack (deploy/run.sh or the grid runner); "
                            "stop it first (Ctrl-C in its terminal), or give another --run.name") from None
    except OSError as error:  # a file system without locks (some network mounts): go on unguarded, and say so
        log.warning("cannot lock %s (%s): a second stack on this run would not be refused", run.stack_lock, error)
    deadline = time.monotonic() + wait_s
    while (lingering := lingering_pids(run)) and time.monotonic() < deadline:
        time.sleep(LINGER_POLL_S)
    if lingering:
        handle.close()
        raise RunClaimError(f"processes of an earlier stack of run folder {run.root} are still alive after "
                            f"{wait_s:.0f} s (pids {', '.join(map(str, lingering))}); they stop by themselves once "
                            "their stack is gone: wait for them, then start again")
    return handle


def lingering_pids(run: RunDir) -> list[int]:
    """The pids in the run's status file of processes alive now and started with the run's config."""
    try:
        status = RunStatus.read(run.status)
    except StatusError:  # no status yet, or a damaged one: nothing known to wait for
        return []
    return sorted(pid for pid in status.pids.values() if _runs_config(pid, run.config))


def _runs_config(pid: int, config: Path) -> bool:
    """Whether process pid was started with --config naming this file (from wherever it was started)."""
    try:
        arguments = [os.fsdecode(item) for item in Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")]
        cwd = Path(os.readlink(f"/proc/{pid}/cwd"))
    except OSError:  # gone, or not ours to read
        return False
    named = [arguments[index + 1] for index, item in enumerate(arguments[:-1]) if item == "--config"]
    return any((cwd / name).resolve() == config.resolve() for name in named)
