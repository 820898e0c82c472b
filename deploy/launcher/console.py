"""The stack's console: its lines on stdout and stderr, for as long as somebody reads them.

A stack whose reader is gone (the grid runner killed, the reading end of a pipe closed, a terminal hung up)
would otherwise fail on its next line, skip stopping its processes and leave them training with nobody to
stop them. Instead it stops the run cleanly (the learner checkpoints; `--resume` goes on), as a Unix writer
stops when its reader goes, and writes nothing more, so that the stop itself cannot fail on a line.
"""

from __future__ import annotations

import os
import select
import sys
import threading

from common.disk_space import is_disk_full

GONE_EVENTS = select.POLLERR | select.POLLHUP  # Linux: a pipe with no reader left; a hung-up terminal


class Console:
    def __init__(self, stop: threading.Event) -> None:
        self.stop = stop  # set once a stream's reader is gone
        self.gone: set[str] = set()  # "stdout", "stderr": silenced

    def say(self, *parts, err: bool = False, end: str = "\n") -> None:
        """print(*parts, sep="") to stdout (or stderr), flushed; nothing once that stream's reader is gone."""
        name = "stderr" if err else "stdout"
        if name in self.gone:
            return
        try:
            print(*parts, sep="", end=end, file=getattr(sys, name), flush=True)
        except OSError as error:  # BrokenPipeError on a closed pipe, EIO on a hung-up terminal
            if not is_disk_full(error):  # a file on a full disk still has its reader: the line alone is lost
                self._lost(name)

    def check(self) -> bool:
        """Whether both streams still have a reader, asked without writing (so a run that prints a line a
        minute notices at once); a lost one stops the run."""
        for name in ("stdout", "stderr"):
            if name not in self.gone and _reader_gone(getattr(sys, name)):
                self._lost(name)
        return not self.gone

    def _lost(self, name: str) -> None:
        self.gone.add(name)
        _silence(getattr(sys, name))
        self.stop.set()


def _reader_gone(stream) -> bool:
    try:
        poller = select.poll()
        poller.register(stream.fileno(), select.POLLOUT)
        return any(events & GONE_EVENTS for _, events in poller.poll(0))
    except (OSError, ValueError, AttributeError):  # no descriptor (a captured stream), or None (fd 1 closed)
        return False


def _silence(stream) -> None:
    """Points the stream's descriptor at /dev/null: what is left in its buffer, and the interpreter's flush
    at exit, go nowhere instead of raising again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, stream.fileno())
        finally:
            os.close(devnull)
    except (OSError, ValueError, AttributeError):
        pass
