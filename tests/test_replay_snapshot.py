"""The replay's snapshot: incremental, atomic, restored whole with its counters, and cheap for the lock."""

import json
import threading

import numpy as np
import pytest

from common.config_values import load_config
from common.wire.frames import FrameStack
from common.wire.messages import Episode, flat_values
from replay.process import counters_path, save_counters
from replay.service import ReplayService
from replay.snapshot import MANIFEST, Snapshotter

SIZE = 36
INCARNATION = 0xABC


def make_config(tmp_path, **overrides):
    return load_config("smoke", overrides={"network.frame_height": SIZE, "network.frame_width": SIZE,
                                           "run.runs_dir": str(tmp_path), "run.name": "snap",
                                           "replay.capacity": 6, **overrides})


def episode(index: int, steps: int = 12, actor: int = 0, incarnation: int = INCARNATION) -> Episode:
    frames = np.full((steps + 1, SIZE, SIZE, 3), index % 256, dtype=np.uint8)
    frames[:, 0, 0, 0] = np.arange(steps + 1)
    return Episode(observations=FrameStack.from_array(frames), actions=np.arange(steps, dtype=np.int64) % 5,
                   rewards=np.linspace(0, 1, steps, dtype=np.float32), terminated=index % 2 == 0, truncated=False,
                   actor_id=actor, start_set="train", start_index=0,
                   weights_version=np.full(steps, index, np.int64), epsilon=1.0, seed=0, episode_index=index,
                   incarnation=incarnation)


def fill(service: ReplayService, indices) -> None:
    for index in indices:
        service.on_episode(episode(index))


def restored_service(config) -> ReplayService:
    service = ReplayService(config)
    restored = service.snapshotter.load(service.shape.frame_shape)
    assert restored is not None
    counters = json.loads(counters_path(config).read_text()) if counters_path(config).exists() else None
    service.restore(restored, counters)
    return service


def stored_content(service: ReplayService) -> list[tuple]:
    return [(stored.seq, stored.frames.decode().tobytes(), stored.actions.tolist(), stored.rewards.tolist(),
             stored.weights_version.tolist(), stored.terminated) for stored in service.store.episodes()]


def test_a_restored_replay_holds_the_same_episodes_and_counters(tmp_path):
    config = make_config(tmp_path)
    service = ReplayService(config)
    fill(service, range(4))
    assert service.write_snapshot()
    again = restored_service(config)
    assert stored_content(again) == stored_content(service)
    before, after = flat_values(service.stats()), flat_values(again.stats())
    for name in ("episodes", "frames", "bytes", "inserted", "env_steps_total", "rate_env_steps",
                 "rate_start_env_steps", "rate_batches_served"):
        assert after[name] == before[name], name
    assert after["restored_episodes"] == 4 and after["rate_refilling"] == 0  # 4 >= start_episodes 2
    # the ledger came back too: the same episode is not stored twice, a new one is
    again.on_episode(episode(3))
    again.on_episode(episode(4))
    latest = flat_values(again.stats())
    assert latest["rejected_episode_duplicate"] == 1 and latest["episodes"] == 5 and latest["inserted"] == 5


def test_each_snapshot_writes_only_new_episodes_and_drops_evicted_segments(tmp_path):
    config = make_config(tmp_path)  # capacity 6
    service = ReplayService(config)
    fill(service, range(3))
    service.write_snapshot()
    first = flat_values(service.stats())
    assert (first["snapshot_episodes"], first["snapshot_written_episodes"]) == (3, 3)
    service.write_snapshot()
    assert flat_values(service.stats())["snapshot_written_episodes"] == 0  # nothing new: only the manifest
    assert flat_values(service.stats())["snapshot_written_bytes"] < 1000
    fill(service, range(3, 10))  # 10 inserted, the 6 newest kept: the first segment is all evicted
    service.write_snapshot()
    latest = flat_values(service.stats())
    assert (latest["snapshot_episodes"], latest["snapshot_written_episodes"]) == (6, 6)  # 4..9; 3 was evicted unsaved
    segments = sorted(path.name for path in service.snapshotter.directory.glob("segment-*"))
    assert segments == ["segment-00000001.bin"]  # the second snapshot wrote no segment
    assert latest["snapshot_bytes"] == sum(path.stat().st_size for path in service.snapshotter.directory.iterdir())
    assert [stored.seq for stored in restored_service(config).store.episodes()] == list(range(4, 10))


def test_a_snapshot_cut_short_leaves_the_previous_one_whole(tmp_path):
    config = make_config(tmp_path)
    service = ReplayService(config)
    fill(service, range(3))
    service.write_snapshot()
    directory = service.snapshotter.directory
    # killed mid-snapshot: a new segment written, the manifest's temporary file half written
    (directory / "segment-00000007.bin").write_bytes(b"\x00" * 100)
    (directory / f".{MANIFEST}.tmp").write_bytes(b"\x85half")
    again = restored_service(config)
    assert [stored.seq for stored in again.store.episodes()] == [0, 1, 2]
    assert not (directory / "segment-00000007.bin").exists()  # the orphan is removed
    fill(again, range(3, 5))
    again.write_snapshot()  # a new segment number, past the orphan's
    assert [stored.seq for stored in restored_service(config).store.episodes()] == [0, 1, 2, 3, 4]


def test_a_damaged_record_is_skipped_and_counted(tmp_path):
    config = make_config(tmp_path)
    service = ReplayService(config)
    fill(service, range(3))
    service.write_snapshot()
    [segment] = service.snapshotter.directory.glob("segment-*")
    data = bytearray(segment.read_bytes())
    data[len(data) // 2] ^= 0xFF  # inside the second record
    segment.write_bytes(bytes(data))
    again = restored_service(config)
    assert [stored.seq for stored in again.store.episodes()] == [0, 2]
    assert flat_values(again.stats())["restore_skipped"] == 1


def test_the_newer_counters_win_and_the_ratio_carries_on(tmp_path):
    """rate_limiter.json is saved every stats period, the snapshot less often: after a kill the
    file's counters are the newer; the store comes from the snapshot."""
    config = make_config(tmp_path)
    service = ReplayService(config)
    fill(service, range(3))  # updates start at the second episode: start mark 24
    service.write_snapshot()
    fill(service, range(3, 5))  # steps that reached the replay after the snapshot, and a batch served
    service.limiter.on_served()
    save_counters(counters_path(config), service.limiter_state())
    again = restored_service(config)
    limiter = again.limiter
    assert (limiter.env_steps, limiter.served, limiter.start_mark) == (60, 1, 24.0)
    assert len(again.store) == 3 and not limiter.refilling
    again.on_episode(episode(5))  # 3 and 4 reached the replay after its snapshot: missing now
    assert flat_values(again.stats())["episodes_missing"] == 2


def test_stale_counters_lose_to_the_snapshot(tmp_path):
    config = make_config(tmp_path)
    service = ReplayService(config)
    save_counters(counters_path(config), service.limiter_state())  # an old file: zero steps
    fill(service, range(3))
    service.write_snapshot()
    assert restored_service(config).limiter.env_steps == 36


def test_the_lock_is_free_while_the_snapshot_is_written(tmp_path):
    config = make_config(tmp_path)
    service = ReplayService(config)
    fill(service, range(3))
    real_write, free = service.snapshotter.write, []

    def write(view):
        free.append(service._lock.acquire(blocking=False))
        service._lock.release()
        fill(service, [10])  # an insert goes through meanwhile
        return real_write(view)

    service.snapshotter.write = write
    assert service.write_snapshot()
    assert free == [True] and flat_values(service.stats())["snapshot_episodes"] == 3 and len(service.store) == 4
    assert flat_values(service.stats())["snapshot_pause_ms"] < 100


def test_a_failing_disk_is_counted_and_the_replay_goes_on(tmp_path):
    config = make_config(tmp_path)
    service = ReplayService(config)
    fill(service, range(2))
    service.snapshotter.directory.parent.mkdir(parents=True)
    service.snapshotter.directory.write_text("a file where the directory should be")
    assert not service.write_snapshot()
    fill(service, [2])
    stats = flat_values(service.stats())
    assert stats["snapshot_failures"] == 1 and stats["episodes"] == 3 and "snapshot_age_s" not in stats


def test_a_snapshot_of_other_frames_is_not_restored(tmp_path):
    config = make_config(tmp_path)
    service = ReplayService(config)
    fill(service, range(2))
    service.write_snapshot()
    other = make_config(tmp_path, **{"network.frame_height": 40})
    restored = Snapshotter(service.snapshotter.directory).load((40, SIZE, 3))
    assert restored.episodes == [] and restored.skipped == 2
    assert ReplayService(other).store.episodes() == []


def test_snapshots_and_inserts_from_threads(tmp_path):
    config = make_config(tmp_path, **{"replay.capacity": 20})
    service = ReplayService(config)
    stop = threading.Event()

    def snapshots():
        while not stop.is_set():
            service.write_snapshot()

    thread = threading.Thread(target=snapshots)
    thread.start()
    try:
        fill(service, range(40))
    finally:
        stop.set()
        thread.join(10)
    service.write_snapshot()
    assert stored_content(restored_service(config)) == stored_content(service)


@pytest.mark.parametrize("incarnation", [0, 5])
def test_duplicates_are_refused_only_for_named_episodes(tmp_path, incarnation):
    service = ReplayService(make_config(tmp_path))
    for _ in range(2):
        service.on_episode(episode(1, incarnation=incarnation))
    assert len(service.store) == (1 if incarnation else 2)


def test_a_snapshot_keeps_the_lstm_state_rows_of_a_stored_state_run(tmp_path):
    config = make_config(tmp_path, **{"learner.stored_state": True, "network.lstm_units": 4})
    service = ReplayService(config)
    for index in range(3):
        with_rows = episode(index)
        with_rows.recurrent_state = np.full((12, 2, 4), index / 4, np.float16)
        service.on_episode(with_rows)
    assert service.write_snapshot()
    again = restored_service(config)
    assert [stored.states.tolist() for stored in again.store.episodes()] == \
           [stored.states.tolist() for stored in service.store.episodes()]
    assert len(again.store.episodes()) == 3
    without = ReplayService(make_config(tmp_path))  # a run without stored states keeps the episodes, not the rows
    restored = without.snapshotter.load(without.shape.frame_shape)
    without.restore(restored, None)
    assert len(without.store) == 3 and all(stored.states is None for stored in without.store.episodes())


def test_a_stored_state_run_refuses_and_counts_episodes_without_fitting_state_rows(tmp_path):
    service = ReplayService(make_config(tmp_path, **{"learner.stored_state": True, "network.lstm_units": 4}))
    service.on_episode(episode(0))  # no rows
    wrong = episode(1)
    wrong.recurrent_state = np.zeros((12, 2, 5), np.float16)  # rows of another network
    service.on_episode(wrong)
    assert len(service.store) == 0
    assert service.rejections.values()["rejected_episode_recurrent_state"] == 2
