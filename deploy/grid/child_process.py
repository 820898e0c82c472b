"""A child process of the grid runner: its output to a log file, its latest status line kept."""

from __future__ import annotations

import re
import signal
import subprocess
import threading
from collections import deque
from pathlib import Path
from typing import Callable

from common.shell import env_stopping_with_this


class Child:
    """A subprocess whose output goes to a log file; keeps its latest status line (those `is_status`
    accepts) and echoes the others.

    It runs in a session of its own, so a Ctrl-C in the terminal reaches it once, forwarded by the runner; and
    it stops by itself once the runner is gone (common/shell.stop_with_parent: the stack and evaluate watch).
    """

    def __init__(self, command: list[str], log_path: Path, is_status: Callable[[str], bool] | None,
                 echo_prefix: str | None) -> None:
        log_path.parent.mkdir(parents=True, exist_ok=True)
        self.log_path = log_path
        self.is_status = is_status
        self.echo_prefix = echo_prefix  # None: other lines stay in the log
        self.latest = ""
        self.tail: deque[str] = deque(maxlen=8)  # for the error message when it fails
        self._log = open(log_path, "ab")
        self.process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                        stdin=subprocess.DEVNULL, start_new_session=True,
                                        env=env_stopping_with_this())  # a runner killed leaves it no work
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        pending = ""
        while chunk := self.process.stdout.read1(65536):
            self._log.write(chunk)
            self._log.flush()
            *lines, pending = re.split(r"[\r\n]", pending + chunk.decode(errors="replace"))
            for line in filter(None, (line.strip() for line in lines)):
                self._take(line)
        if pending.strip():
            self._take(pending.strip())

    def _take(self, line: str) -> None:
        if self.is_status is not None and self.is_status(line):
            self.latest = line
            return
        self.tail.append(line)
        if self.echo_prefix is not None:
            print(f"{self.echo_prefix}: {line}", flush=True)

    def interrupt(self) -> None:
        """SIGINT, once: the stack stops its processes (the learner checkpoints), evaluate stops its workers."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)

    def wait(self) -> int:
        code = self.process.wait()
        self._reader.join()
        self._log.close()
        return code

