"""A fake full disk for one file: the path (or the temporary a write-then-rename writes first) links to /dev/full,
where every write fails with ENOSPC, as on a disk with no block left."""

from __future__ import annotations

import os
from pathlib import Path

from common.atomic_file import temporary_path

FULL_DEVICE = Path("/dev/full")


def full_at(path: Path) -> Path:
    """Writes to `path` fail with ENOSPC from now on; returns it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    os.symlink(FULL_DEVICE, path)
    return path


def full_for(path: Path) -> Path:
    """The next write-then-rename of `path` by this process fails with ENOSPC; returns the temporary it would
    have left behind."""
    return full_at(temporary_path(path))


def space_returns(path: Path) -> None:
    """Undoes full_at / full_for on that path (a failed write removed it already where it ran)."""
    if path.is_symlink():
        path.unlink()
