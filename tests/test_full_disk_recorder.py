"""The recorder on a full disk pauses instead of dying: the file so far reads back, what arrives meanwhile is
dropped and counted, and once space returns the recording goes on in the next file."""

from __future__ import annotations

import os
import time

from common.run_dir import next_free_path
from common.wire.envelope import encode
from common.wire.messages import Stats
from full_disk import FULL_DEVICE
from replay.recorder.reader import LogFile
from replay.recorder.recorder import Recorder
from replay.recorder.writer import LogWriter
from tests.test_log import small_config

KEY = "d3rqn/default/metrics/learner/0"


def stats(index: int) -> bytes:
    return encode(Stats(source="learner", time=float(index + 1), values={"i": index}))


def wait_until(condition, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


def test_a_full_disk_pauses_the_recording_which_goes_on_in_the_next_file_once_space_returns(tmp_path):
    config = small_config()
    first = tmp_path / "traffic.mcap"
    free = {"bytes": 0}
    recorder = Recorder(LogWriter.open(first, config, None), config.recorder,
                        reopen=lambda: LogWriter.open(next_free_path(first), config, None),
                        free_space=lambda: free["bytes"])
    recorder.start()
    for index in range(3):
        recorder.offer(KEY, stats(index), index + 1)
    wait_until(lambda: recorder.writer.flushed_bytes and recorder.writer.messages == 3
               and recorder.handoff.depth()[0] == 0)
    time.sleep(2 * config.recorder.flush_period_s)  # a flush after the third message
    with open(first, "ab") as part:  # the disk takes the start of the next chunk, then fills
        part.write(b"\x06" + b"\xff" * 20)
    full = os.open(FULL_DEVICE, os.O_WRONLY)
    os.dup2(full, recorder.writer._file.fileno())
    os.close(full)
    recorder.offer(KEY, stats(3) * 50, 4)
    wait_until(lambda: recorder.snapshot()["paused"] == 1)
    recorder.offer(KEY, stats(4), 5)  # while paused: dropped, counted
    wait_until(lambda: recorder.snapshot()["dropped"] == 1)
    assert not (tmp_path / "traffic-2.mcap").exists()
    free["bytes"] = recorder.resume_bytes  # space returns
    wait_until(lambda: recorder.snapshot()["paused"] == 0)
    recorder.offer(KEY, stats(5), 6)
    recorder.stop()

    with LogFile(first, unfinished_ok=True) as log:
        assert [record.data for record in log.records()] == [stats(index) for index in range(3)]
    with LogFile(tmp_path / "traffic-2.mcap") as log:  # whole: it was closed
        assert [record.data for record in log.records()] == [stats(5)]
        assert log.recorder_counters()["pauses"] == "1"
    assert recorder.error is None and recorder.snapshot()["written"] == 4 and recorder.path.name == "traffic-2.mcap"


def test_a_log_whose_beginning_cannot_be_written_leaves_no_file(tmp_path):
    config = small_config()
    target = tmp_path / "traffic-2.mcap"
    os.symlink(FULL_DEVICE, target)
    try:
        LogWriter.open(target, config, None)
    except OSError as error:
        assert error.errno == 28
    else:
        raise AssertionError("a write to /dev/full succeeded")
    assert not target.exists() and not target.is_symlink()
