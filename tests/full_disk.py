"""Full disks for tests. For one file: the path (or the temporary a write-then-rename writes first) links to
/dev/full, where every write fails with ENOSPC, as on a disk with no block left. For a whole run: a tmpfs (root
only), filled and emptied under it."""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import threading
import time
from pathlib import Path

from common.atomic_file import temporary_path
from common.disk_space import free_bytes

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


class Tmpfs:
    """A tmpfs mounted for a lab test, which fill() fills with a ballast file that a thread keeps topped up (what
    the run frees is taken at once, as on a disk shared with others) until room() deletes it."""

    def __init__(self, path: Path, size_mb: int) -> None:
        self.path = path
        self.size_mb = size_mb
        self.ballast = path / "ballast"
        self._stop = threading.Event()
        self._keeper: threading.Thread | None = None
        self.mounted = False

    def mount(self) -> None:
        self.path.mkdir(parents=True, exist_ok=True)
        subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={self.size_mb}m", "tmpfs", str(self.path)],
                       check=True, capture_output=True, text=True)
        self.mounted = True

    def fill(self) -> None:
        self._stop.clear()
        self._keeper = threading.Thread(target=self._keep_full, name="ballast", daemon=True)
        self._keeper.start()
        deadline = time.monotonic() + FILL_WAIT_S
        while (free_bytes(self.path) or 0) > CHUNK:
            if time.monotonic() > deadline or not self._keeper.is_alive():
                raise AssertionError(f"{self.path} did not fill within {FILL_WAIT_S:.0f} s")
            time.sleep(0.05)

    def room(self) -> None:
        self._stop.set()
        if self._keeper is not None:
            self._keeper.join(10.0)
        self.ballast.unlink(missing_ok=True)

    def unmount(self) -> None:
        self.room()
        if self.mounted:
            subprocess.run(["umount", "-l", str(self.path)], capture_output=True)
            self.mounted = False

    def _keep_full(self) -> None:
        with open(self.ballast, "ab", buffering=0) as ballast:
            while not self._stop.is_set():
                for size in (CHUNK, 4096):
                    with contextlib.suppress(OSError):  # ENOSPC: full for now
                        while not self._stop.is_set():
                            ballast.write(bytes(size))
                self._stop.wait(0.1)


CHUNK = 1 << 20
FILL_WAIT_S = 30.0


def why_no_tmpfs() -> str | None:
    """Why a tmpfs cannot be mounted here; None where it can be tried."""
    if os.geteuid() != 0:
        return "mounting a tmpfs needs root"
    if shutil.which("mount") is None or shutil.which("umount") is None:
        return "no mount(8) here"
    return None
