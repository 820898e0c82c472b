"""Write-then-rename, the one way a run's files are replaced: a reader, or a crash, sees the old file or the new
one, and a failed write (a full disk) leaves no part of the new one behind.

The temporary lies next to the file as .<name>.<pid>.tmp. A process killed mid-write still leaves its own, so a
role at start removes those of processes that are gone (remove_dead_temporaries): on a full disk each would
hold up to a checkpoint's size.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
from pathlib import Path
from typing import BinaryIO, Callable

log = logging.getLogger(__name__)

TEMPORARY = re.compile(r"\..+\.(\d+)\.tmp")


def temporary_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def write_atomically(path: Path, write: Callable[[BinaryIO], object]) -> Path:
    """write(handle) into a temporary file, synced, then renamed over `path`; on any failure the temporary goes
    and the error is raised."""
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = temporary_path(path)
    try:
        with open(temporary, "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except BaseException:
        with contextlib.suppress(OSError):  # removing frees space: it cannot fail for want of it
            temporary.unlink(missing_ok=True)
        raise
    return path


def write_text_atomically(path: Path, text: str) -> Path:
    return write_atomically(path, lambda handle: handle.write(text.encode()))


def remove_dead_temporaries(*folders: Path) -> int:
    """Removes the temporaries in the folders, and in theirs, whose process is gone; returns their bytes."""
    removed = 0
    for folder in folders:
        for path in _temporaries(folder):
            match = TEMPORARY.fullmatch(path.name)
            if match is None or pid_alive(int(match[1])):
                continue
            try:
                size = path.stat().st_size
                path.unlink()
            except OSError:  # another role's start removed it first
                continue
            removed += size
            log.info("removed %s, %d bytes, which a stopped process left half-written", path, size)
    return removed


def _temporaries(folder: Path) -> list[Path]:
    try:
        return [path for path in folder.rglob(".*.tmp") if path.is_file()]
    except OSError:  # a folder removed meanwhile
        return []


def pid_alive(pid: int) -> bool:
    """Whether a process of this machine has the pid (this one included)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's
        return True
    return True
