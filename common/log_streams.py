"""stdout and stderr that a full disk cannot end a process through.

A role's log is its stderr, a file in the run folder. On a full disk a print there raises OSError (ENOSPC), and
the first one, the config printed at start, ended every restarted learner before its first line. Each stream is
replaced by one that writes straight to its descriptor (no buffer keeps a line that failed, to come out later
half-written), drops what the disk refuses, and says, once space returns, how many writes it dropped. Any other
error (a pipe with no reader) is raised as before: the stack's console stops on it.
"""

from __future__ import annotations

import os
import sys

from common.disk_space import is_disk_full


class DiskTolerantStream:
    """A text stream over a descriptor; the writes a full disk refuses are dropped and counted."""

    def __init__(self, stream) -> None:
        self._stream = stream
        self._fd = stream.fileno()
        self.encoding = getattr(stream, "encoding", None) or "utf-8"
        self.dropped = 0  # writes lost since the last that succeeded
        self.dropped_total = 0

    def write(self, text: str) -> int:
        data = text.encode(self.encoding, "backslashreplace")
        if self.dropped:
            data = f"\n[{self.dropped} writes to this log lost: the disk was full]\n".encode() + data
        try:
            self._write_all(data)
        except OSError as error:
            if not is_disk_full(error):
                raise
            self.dropped += 1
            self.dropped_total += 1
            return len(text)
        self.dropped = 0
        return len(text)

    def _write_all(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self._fd, view):]

    def flush(self) -> None:
        """Nothing is held back."""

    def fileno(self) -> int:
        return self._fd

    def isatty(self) -> bool:
        return os.isatty(self._fd)

    def writable(self) -> bool:
        return True

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def tolerate_full_disk() -> None:
    """Replaces sys.stdout and sys.stderr, where each has a descriptor, by a DiskTolerantStream over it."""
    for name in ("stdout", "stderr"):
        stream = getattr(sys, name)
        if isinstance(stream, DiskTolerantStream):
            continue
        try:
            stream.flush()
            stream.fileno()
        except (OSError, ValueError, AttributeError):  # no descriptor: a captured stream, or one closed
            continue
        setattr(sys, name, DiskTolerantStream(stream))
