"""A full disk: how much the run's disk has free, whether an error is the disk being full, and a file that cannot
be written said once per spell, not at every try, while the process goes on.

A role that ends for a full disk all the same exits with DISK_FULL_EXIT; the stack then restarts it once space
returns, not in a loop (deploy/launcher/stack.py).
"""

from __future__ import annotations

import errno
import logging
import os
from pathlib import Path
from typing import Callable

DISK_FULL_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT})
DISK_FULL_EXIT = 75  # EX_TEMPFAIL of sysexits.h: try again later
MEGABYTE = 1 << 20


def free_bytes(path: Path) -> int | None:
    """The bytes this user may still write on the filesystem that holds `path` (or its nearest folder that
    exists); None where the system cannot say."""
    for folder in (path, *path.parents):
        try:
            stats = os.statvfs(folder)
        except FileNotFoundError:
            continue
        except OSError:
            return None
        return stats.f_bavail * stats.f_frsize
    return None


def is_disk_full(error: BaseException | None) -> bool:
    """Whether the error, or one it arose from, is a full disk or quota (torch wraps the OSError of a write in
    a RuntimeError of its own)."""
    seen = set()
    while error is not None and id(error) not in seen:
        seen.add(id(error))
        if isinstance(error, OSError) and error.errno in DISK_FULL_ERRNOS:
            return True
        error = error.__cause__ or error.__context__
    return False


def size_text(count: int | None) -> str:
    """A size for a log line: in MB, or in bytes below one."""
    if count is None:
        return "an unknown amount"
    return f"{count:,d} bytes" if count < MEGABYTE else f"{count / MEGABYTE:,.1f} MB"


def file_bytes(path: Path) -> int | None:
    try:
        return path.stat().st_size
    except OSError:
        return None


class RetriedWrites:
    """Writes of one file that is rewritten now and then (a checkpoint): one that fails (a full disk) leaves the
    last one written in place and is one line, with the bytes it needs and those free, for the first failure of
    a spell; the first write that succeeds after it is another. The caller tries again when the next is due."""

    def __init__(self, what: str, target: Path, logger: logging.Logger) -> None:
        self.what = what
        self.target = target
        self.log = logger
        self.failing = 0  # failures since the last write that succeeded
        self.failed = 0  # in all

    def attempt(self, write: Callable[[], Path]) -> Path | None:
        """write()'s path, or None where it failed."""
        try:
            path = write()
        except (OSError, RuntimeError) as error:  # torch raises RuntimeError for an OSError underneath
            self._failed(error)
            return None
        if self.failing:
            self.log.info("wrote the %s again, after %d failed tries: %s", self.what, self.failing, path)
        self.failing = 0
        return path

    def _failed(self, error: BaseException) -> None:
        self.failing += 1
        self.failed += 1
        if self.failing > 1:
            return
        kept = "the last one written stays" if self.target.exists() else "there is none yet"
        reason = "the disk is full" if is_disk_full(error) else f"{type(error).__name__}: {error}"
        self.log.error("cannot write the %s %s (%s): it needs about %s, %s free; %s, and the next one due is "
                       "tried (said once until one is written)", self.what, self.target, reason,
                       size_text(file_bytes(self.target)), size_text(free_bytes(self.target.parent)), kept)
