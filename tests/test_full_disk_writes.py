"""A full disk under each write-then-rename of a run (checkpoints, kept policies, status, summary, config, the
replay's counters and snapshot): the write fails, the last good file stays whole, and no part of the new one is
left behind. The learner trains on through a checkpoint it cannot write, and says so once."""

from __future__ import annotations

import errno
import logging
import subprocess
import sys
import threading

import pytest
import torch

from common.atomic_file import remove_dead_temporaries, temporary_path, write_text_atomically
from common.checkpoint import KeptPolicy, save_checkpoint
from common.disk_space import is_disk_full
from common.run_dir import RunStatus
from full_disk import full_at, full_for, space_returns
from replay.process import save_counters
from replay.service import ReplayService
from tests.test_learner_resume import batches, config, started, train  # noqa: F401 - the fixture
from tests.test_replay_snapshot import fill, make_config


def policy() -> KeptPolicy:
    return KeptPolicy(updates=3, env_steps=10, wall_s=1.0, cpu="test", config={}, online={"w": torch.ones(4)})


WRITERS = {
    "checkpoint": ("latest.pt", lambda path: save_checkpoint(path.parent, {"learner": {"updates": 1}})),
    "kept policy": ("policy-u0000003.pt", lambda path: policy().save(path)),
    "status": ("status.json", lambda path: RunStatus(phase="training").write(path)),
    "summary or config": ("summary.json", lambda path: write_text_atomically(path, "{}\n")),
    "counters": ("rate_limiter.json", lambda path: save_counters(path, {"env_steps": 1})),
}


@pytest.mark.parametrize("kind", WRITERS)
def test_a_write_on_a_full_disk_fails_leaving_the_last_good_file_and_no_temporary(tmp_path, kind):
    name, write = WRITERS[kind]
    path = tmp_path / name
    write(path)
    good = path.read_bytes()
    temporary = full_for(path)
    with pytest.raises((OSError, RuntimeError)) as raised:
        write(path)
    assert is_disk_full(raised.value), raised.value
    assert path.read_bytes() == good
    assert not temporary.exists() and not temporary.is_symlink()
    write(path)  # space came back
    assert not list(tmp_path.glob(".*.tmp"))


def test_a_snapshot_on_a_full_disk_leaves_the_last_one_and_no_part(tmp_path):
    config = make_config(tmp_path)
    service = ReplayService(config)
    fill(service, range(2))
    assert service.write_snapshot()
    directory = service.snapshotter.directory
    before = sorted(path.name for path in directory.iterdir())
    fill(service, [2])
    segment = full_at(directory / "segment-00000001.bin")
    assert not service.write_snapshot()
    assert sorted(path.name for path in directory.iterdir()) == before  # the part segment went
    fill(service, [3])
    temporary = full_for(directory / "manifest.msgpack")
    assert not service.write_snapshot()
    assert not temporary.is_symlink() and not list(directory.glob(".*.tmp"))
    assert service.snapshot_stats["snapshot_failures"] == 2
    space_returns(segment)
    assert service.write_snapshot()  # space came back: every episode is in it
    assert service.snapshot_stats["snapshot_episodes"] == 4


def test_temporaries_of_dead_processes_are_removed_and_live_ones_kept(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    pid = int(dead.stdout)
    (tmp_path / "checkpoints").mkdir()
    left = tmp_path / "checkpoints" / f".latest.pt.{pid}.tmp"
    left.write_bytes(b"x" * 1000)
    own = temporary_path(tmp_path / "status.json")
    own.write_bytes(b"y")
    stranger = tmp_path / "notes.tmp"
    stranger.write_bytes(b"z")
    assert remove_dead_temporaries(tmp_path) == 1000
    assert not left.exists() and own.exists() and stranger.exists()


def test_the_learner_trains_on_through_a_full_disk_and_says_so_once(config, caplog):
    config.learner.checkpoint_every, config.learner.checkpoint_every_s = 1, 0.0
    process = started(config)
    data = batches(6)
    train(process, data[0])
    process.checkpoint_if_due()
    target = process.checkpoint_dir / "latest.pt"
    good = target.read_bytes()
    with caplog.at_level(logging.INFO, logger="learner"):
        for batch in data[1:4]:
            temporary = full_for(target)
            train(process, batch)
            process.checkpoint_if_due()
            assert not temporary.is_symlink()
        assert process.updates == 4 and target.read_bytes() == good
        said = [record.getMessage() for record in caplog.records if "cannot write the checkpoint" in record.message]
        assert len(said) == 1 and "the disk is full" in said[0] and " free;" in said[0], said
        train(process, data[4])
        process.checkpoint_if_due()
    assert torch.load(target, weights_only=True)["learner"]["updates"] == 5
    assert any("again, after 3 failed tries" in record.message for record in caplog.records)
    assert not list(process.checkpoint_dir.glob(".*.tmp"))


def test_an_oserror_that_is_not_a_full_disk_is_not_called_one():
    assert not is_disk_full(OSError(errno.EACCES, "denied"))
    try:
        try:
            raise OSError(errno.ENOSPC, "No space left on device")
        except OSError:
            raise RuntimeError("unexpected pos 576 vs 534")
    except RuntimeError as error:
        assert is_disk_full(error)


class Receiver:
    rejected = 0


def test_the_replay_serves_on_through_counters_it_cannot_save_and_says_so_once(tmp_path, caplog):
    from replay import process as replay_process
    config = make_config(tmp_path, **{"replay.stats_period_s": 0.01})
    service = ReplayService(config)
    path = replay_process.counters_path(config)
    stop, sent = threading.Event(), []

    def put(stats) -> None:  # the stats go out every period; the counters' file is tried after each
        sent.append(stats)
        if len(sent) <= 4:
            full_for(path)
        if len(sent) == 5:  # space returns
            stop.set()

    outlet = type("Outlet", (), {"put": staticmethod(put)})
    with caplog.at_level(logging.INFO, logger="replay"):
        replay_process._report_until(stop, service, {"episodes": Receiver()}, outlet, config, path)
    said = [record.getMessage() for record in caplog.records if "rate limiter's counters" in record.getMessage()]
    assert len(sent) == 5 and len(said) == 2 and "the disk is full" in said[0], said
    assert "again, after 4 failed tries" in said[1]
    assert path.exists() and not list(path.parent.glob(".*.tmp"))
