"""The heap's free pages handed back (common/malloc_trim.py): after a burst of frames made and freed, a process
holds its peak until malloc_trim; without the call (not glibc) one log line, and nothing else."""

import logging
import subprocess
import sys
import types

import pytest

from common import malloc_trim

BURST = """
import resource, sys
from common.malloc_trim import release_free_heap

def rss_mb():
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * resource.getpagesize() / 1e6

frames = [bytearray(40_000) for _ in range(5_000)]  # 200 MB of frames of 66 x 200 x 3, as a random phase makes
pin = bytearray(40_000)  # a later allocation on top: the heap cannot shrink from its end
del frames
before = rss_mb()
released = release_free_heap()
print(released, before, rss_mb())
"""


def test_a_burst_freed_goes_back_to_the_system():
    result = subprocess.run([sys.executable, "-c", BURST], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    released, before, after = result.stdout.split()
    if released == "None":
        pytest.skip("this C library has no malloc_trim (not glibc)")
    assert released == "True" and float(before) - float(after) > 150, result.stdout


def test_a_c_library_without_malloc_trim_is_said_once_and_nothing_breaks(monkeypatch, caplog):
    malloc_trim._malloc_trim.cache_clear()
    monkeypatch.setattr(malloc_trim.ctypes, "CDLL", lambda _: types.SimpleNamespace())
    try:
        with caplog.at_level(logging.INFO, logger="common.malloc_trim"):
            assert malloc_trim.release_free_heap() is None and malloc_trim.release_free_heap() is None
        assert [record.getMessage() for record in caplog.records] == [
            "this C library has no malloc_trim (it is not glibc): memory freed after a burst stays with the process"]
    finally:
        malloc_trim._malloc_trim.cache_clear()


ROLE = """
import threading, time
from common import malloc_trim, shell
from common.config import Config
calls = []
malloc_trim.TRIM_PERIOD_S = 0.01
malloc_trim.release_free_heap = lambda: calls.append(1) or True
role = shell.Shell("replay", Config())
time.sleep(0.5)
role.stop.set()
thread = next(t for t in threading.enumerate() if t.name == "heap-trim")
thread.join(5)
print(len(calls), thread.is_alive())
"""


def test_every_role_keeps_releasing_from_its_shell_until_it_stops():
    """In its own process: the shell sets signal handlers and a log."""
    result = subprocess.run([sys.executable, "-c", ROLE], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    calls, alive = result.stdout.split()
    assert int(calls) >= 10 and alive == "False", result.stdout
