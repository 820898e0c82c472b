"""The stack's eye on its run folder's disk: the free space for the live line and the status file, a warning while
it is less than the next checkpoint and snapshot need, and whether a process that ended for a full disk may
start again (deploy/launcher/stack.py waits until it may, instead of restarting it into the same wall)."""

from __future__ import annotations

from typing import Callable

from common.disk_space import MEGABYTE, file_bytes, free_bytes, size_text
from common.run_dir import RunDir
from replay.snapshot import MANIFEST, SEGMENT_PREFIX, SEGMENT_SUFFIX

START_MIN_BYTES = 16 * MEGABYTE  # what a process started again needs at the least: its log lines, a first file


class DiskWatch:
    def __init__(self, run: RunDir, say: Callable[[str], None],
                 free_space: Callable[[], int | None] | None = None) -> None:
        self.run = run
        self.say = say  # a line to the stack's console
        self._free_space = free_space or (lambda: free_bytes(run.root))
        self.short = False  # the free space is below what the next writes need (said once per spell)
        self.free: int | None = None  # at the last look

    def needed(self) -> int:
        """The bytes the next checkpoint and snapshot take: a checkpoint is written whole beside the last one,
        a snapshot adds a segment like its newest and rewrites its manifest."""
        snapshot = self.run.replay_snapshot
        segments = sorted(snapshot.glob(f"{SEGMENT_PREFIX}*{SEGMENT_SUFFIX}")) if snapshot.is_dir() else []
        sizes = [file_bytes(self.run.checkpoint), file_bytes(snapshot / MANIFEST),
                 file_bytes(segments[-1]) if segments else None]
        return sum(size or 0 for size in sizes)

    def look(self) -> int | None:
        """The free bytes now; warns when they fall below needed(), and says when they are enough again."""
        self.free = self._free_space()
        if self.free is None:
            return None
        needed = self.needed()
        if not self.short and self.free < needed:
            self.short = True
            self.say(f"the disk of {self.run.root} has {size_text(self.free)} free, less than the next checkpoint "
                     f"and snapshot need ({size_text(needed)}): they fail until space is freed, while training goes "
                     "on (docs/reliability.md)")
        elif self.short and self.free >= needed:
            self.short = False
            self.say(f"the disk of {self.run.root} has room again: {size_text(self.free)} free")
        return self.free

    def room_to_start(self) -> bool:
        """Whether a process that ended for a full disk may start again."""
        free = self._free_space()
        return free is None or free >= max(self.needed(), START_MIN_BYTES)
