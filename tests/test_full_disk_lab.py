"""A full disk under a running stack, for real: the run folder on a tmpfs that a ballast file fills while the smoke
stack trains, then frees. No process crash-loops (each role keeps its one pid), the learner's updates go on
rising while the disk is full, the recorder's files read back, no temporary remains, checkpoints and snapshots
are written again once space returns, a stack stopped while the disk is full again exits cleanly without its
summary, and `--resume` continues from the newest checkpoint written. The test prints its figures and leaves
them in full_disk.json.

Needs root to mount the tmpfs; skipped with the reason elsewhere. Run alone, after the rest (deploy/test.sh).
"""

from __future__ import annotations

import json
import re
import subprocess
import threading
import time
from collections import defaultdict

import pytest

from common.checkpoint import Checkpoint, CheckpointError
from common.run_dir import RunDir
from full_disk import Tmpfs, why_no_tmpfs
from replay.recorder.reader import LogFile
from tests.stack_run import StackRun

pytestmark = pytest.mark.lab

FLAGS = ("--learner.checkpoint_every", "1000000", "--learner.checkpoint_every_s", "3", "--learner.keep_every", "0",
         "--learner.keep_every_s", "5", "--replay.snapshot_period_s", "3", "--recorder.flush_period_s", "0.5")
FULL_S = 30.0  # how long the disk stays full: a dozen checkpoints, snapshots and recorder flushes refused
STOP_FULL_S = 8.0  # full again before the stack is stopped: a checkpoint or two refused first
DISK_MB = 512


class Pids:
    """Every pid each role of a stack had, sampled twice a second: more than one is a restart."""

    def __init__(self, run: StackRun) -> None:
        self.run = run
        self.seen: dict[str, set[int]] = defaultdict(set)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()

    def _sample(self) -> None:
        while not self._stop.wait(0.5):
            for role, pid in self.run.roles().items():
                self.seen[role].add(pid)

    def restarts(self) -> dict[str, int]:
        self._stop.set()
        self._thread.join(5.0)
        return {role: len(pids) - 1 for role, pids in sorted(self.seen.items())}


def checkpoint_updates(run: RunDir) -> int:
    try:
        return Checkpoint.load(run.checkpoints).updates or 0
    except CheckpointError:
        return 0


@pytest.fixture
def disk(tmp_path):
    reason = why_no_tmpfs()
    if reason is not None:
        pytest.skip(reason)
    tmpfs = Tmpfs(tmp_path / "disk", DISK_MB)
    try:
        tmpfs.mount()
    except (subprocess.CalledProcessError, OSError) as error:
        pytest.skip(f"cannot mount a tmpfs here: {getattr(error, 'stderr', '') or error}")
    try:
        yield tmpfs
    finally:
        tmpfs.unmount()


def test_a_stack_on_a_disk_that_fills_trains_on_and_writes_again_once_space_returns(tmp_path, disk):
    figures = {}
    stack = StackRun(disk.path, "full", actors=1, flags=FLAGS)
    stack.out_path = tmp_path / "stack.out"  # the stack's console: a terminal, not the full disk
    run = RunDir(stack.run_dir)
    with stack:
        stack.wait(lambda w: w.updates() >= 10 and w.replay.get("snapshots_written", 0) >= 1
                   and checkpoint_updates(run) > 0, "updates, a snapshot and a checkpoint", timeout_s=240)
        pids = Pids(stack)
        _through_a_full_spell(stack, run, disk, figures)
        figures["restarts"] = pids.restarts()
        _stopped_on_a_full_disk(stack, run, disk, figures)
    figures["temporary_bytes_left"] = sum(path.stat().st_size for path in run.root.rglob(".*.tmp"))
    figures["recorder_files"] = {path.name: _records(path) for path in run.wire_log_segments()}
    figures["said"] = _said(run, stack.out_path)
    figures["resumed_from"] = _resume(tmp_path, disk, figures["checkpoint_at_stop"])
    print("\nfull disk:", json.dumps(figures, indent=1))
    (tmp_path / "full_disk.json").write_text(json.dumps(figures, indent=1))

    assert set(figures["restarts"]) >= {"replay", "learner", "recorder", "actor-0"}
    assert not any(figures["restarts"].values()), figures["restarts"]
    assert figures["updates_after_full_s"] > figures["updates_when_full"] + 5, "updates stood still on a full disk"
    assert figures["checkpoint_while_full"] < figures["updates_after_full_s"] < figures["checkpoint_after_room"]
    assert figures["snapshot_failures_while_full"] >= 1 and figures["checkpoints_failed"] >= 1
    assert figures["stack_exit"] == 0 and figures["summary_written"] is False
    assert any("cannot write the summary" in line for line in figures["said"])
    assert any(line.endswith("no summary written") for line in figures["said"])
    assert figures["temporary_bytes_left"] == 0
    assert len(figures["recorder_files"]) >= 2 and all(figures["recorder_files"].values()), "the recorder paused"
    assert figures["resumed_from"] == figures["checkpoint_at_stop"] >= figures["checkpoint_after_room"]


def _through_a_full_spell(stack: StackRun, run: RunDir, disk: Tmpfs, figures: dict) -> None:
    """The disk full for FULL_S while the stack trains, then room again until a checkpoint and snapshots come."""
    figures["updates_when_full"] = stack.watch.updates()
    figures["checkpoint_when_full"] = checkpoint_updates(run)
    disk.fill()
    failures_before = stack.watch.replay.get("snapshot_failures", 0)
    time.sleep(FULL_S)
    figures["updates_after_full_s"] = stack.watch.updates()
    figures["checkpoint_while_full"] = checkpoint_updates(run)  # the last good one, still readable
    figures["snapshot_failures_while_full"] = stack.watch.replay.get("snapshot_failures", 0) - failures_before
    disk.room()
    written = stack.watch.replay.get("snapshots_written", 0)
    stack.wait(lambda w: checkpoint_updates(run) > figures["updates_after_full_s"]
               and w.replay.get("snapshots_written", 0) > written + 1, "a checkpoint and snapshots again",
               timeout_s=60)
    figures["checkpoint_after_room"] = checkpoint_updates(run)
    figures["checkpoints_failed"] = stack.watch.learner.get("checkpoints_failed")


def _stopped_on_a_full_disk(stack: StackRun, run: RunDir, disk: Tmpfs, figures: dict) -> None:
    """Ctrl-C to the stack while the disk is full again: a clean stop, no summary, the newest checkpoint kept."""
    disk.fill()
    time.sleep(STOP_FULL_S)
    figures["stack_exit"] = stack.stop()
    figures["updates_at_stop"] = stack.watch.updates()
    figures["summary_written"] = run.summary.exists()
    disk.room()
    figures["checkpoint_at_stop"] = checkpoint_updates(run)  # the newest that was written


def _said(run: RunDir, console) -> list[str]:
    """What the stack's console and the roles' logs said of the disk."""
    lines = console.read_text(errors="replace").replace("\r", "\n").splitlines()
    for path in sorted(run.logs.glob("*.log")):
        lines += [f"{path.stem}: {line}" for line in path.read_text(errors="replace").splitlines()]
    wanted = ("disk", "cannot write", "again, after", "lost", "space", "summary")
    return [line.strip() for line in lines if any(word in line for word in wanted) and not line.startswith("[")]


def _records(path) -> int:
    with LogFile(path, unfinished_ok=True) as log:
        return sum(1 for _ in log.records())


def _resume(tmp_path, disk: Tmpfs, saved: int) -> int:
    """Starts the stack again with --resume; the updates its learner says it resumed from."""
    again = StackRun(disk.path, "full", actors=1, flags=(*FLAGS, "--resume"))
    again.out_path = tmp_path / "resumed.out"
    with again:
        again.wait(lambda w: w.updates() > saved, "the resumed learner's updates", timeout_s=180)
    log = RunDir(again.run_dir).log("learner").read_text()
    resumed = [line for line in log.splitlines() if "resumed from" in line]
    assert resumed, log[-2000:]
    return int(re.search(r"resumed from .*?: (\d+) updates", resumed[-1])[1])
