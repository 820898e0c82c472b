"""deploy/labs/soak.py: what one sample reads of a run, and the growth figures of its summary, from hand-made rows."""

import csv
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from common.run_dir import RunDir, RunStatus
from common.wire.frames import FrameStack
from deploy.labs import soak
from replay.snapshot import MANIFEST, SnapshotView, Snapshotter, manifest_held
from replay.store import StoredEpisode
from tests.processes import alive, wait_for


def test_a_sample_reads_the_processes_memory_and_the_folders_parts(tmp_path):
    run = RunDir(tmp_path / "run")
    run.replay_snapshot.mkdir(parents=True)
    (run.replay_snapshot / "episodes-1").write_bytes(b"x" * 3000)
    run.wire_log.write_bytes(b"y" * 500)
    run.wire_log.with_name("traffic-2.mcap").write_bytes(b"z" * 20)  # a recorder restarted
    RunStatus("finished", env_steps=1234, updates=300, restarts={"learner": 2, "replay": 1},
              pids={"learner": os.getpid(), "replay": 2**22 + 17}).write(run.status)
    assert soak.main([str(run.root), "--every", "0.01"]) == 0  # one sample: the stack no longer trains
    [row] = list(csv.DictReader((run.soak / "soak.csv").open()))
    assert (row["phase"], row["env_steps"], row["updates"], row["restarts"]) == ("finished", "1234", "300", "3")
    assert float(row["rss_mb_learner"]) > 10 and row["rss_mb_replay"] == "nan"  # this process; a pid that is gone
    assert (row["bytes_log"], row["bytes_snapshot"], row["bytes_checkpoints"]) == ("520", "3000", "0")
    assert (run.soak / "soak.png").stat().st_size > 0
    assert json.loads((run.soak / "soak_summary.json").read_text())["samples"] == 1


def rows(hours: int, learner_mb, folder_mb) -> list[dict]:
    return [{"time": 3600.0 * hour, "elapsed_s": 0, "phase": "training", "env_steps": 100 * hour,
             "updates": 25 * hour, "restarts": hour // 2, "rss_mb_learner": learner_mb(hour), "rss_mb_replay": 300.0,
             **{f"bytes_{part}": 0 for part in soak.PARTS}, "bytes_log": int(folder_mb(hour) * 2**20)}
            for hour in range(hours + 1)]


def test_the_summary_reads_growth_per_hour_from_the_second_half():
    # the learner grows 100 MB an hour for two hours (filling up), then stays flat; the log grows 50 MB an hour
    summary = soak.summarize(rows(4, lambda hour: 500.0 + 100 * min(hour, 2), lambda hour: 50.0 * hour))
    assert summary["memory"]["learner"]["second_half_mb_per_hour"] == pytest.approx(0.0, abs=1e-9)
    assert summary["memory"]["learner"]["max_mb"] == 700.0
    assert summary["memory"]["replay"]["second_half_mb_per_hour"] == pytest.approx(0.0, abs=1e-9)
    assert summary["folder_mb_per_hour"] == pytest.approx(50.0)
    assert summary["folder_mb_per_hour_by_part"]["log"] == pytest.approx(50.0)
    assert (summary["hours"], summary["restarts"], summary["updates"]) == (4.0, 2, 100)
    leaking = soak.summarize(rows(4, lambda hour: 500.0 + 30 * hour, lambda hour: 0.0))
    assert leaking["memory"]["learner"]["second_half_mb_per_hour"] == pytest.approx(30.0)
    assert math.isnan(soak.slope_per_hour(soak.np.array([1.0]), soak.np.array([5.0])))


def test_a_process_never_seen_has_no_row_in_the_summary():
    unseen = [{**row, "rss_mb_curve": math.nan} for row in rows(4, lambda hour: 500.0, lambda hour: 0.0)]
    summary = soak.summarize(unseen)
    assert set(summary["memory"]) == {"learner", "replay"}
    assert "nan" not in soak.summary_text(summary)


def test_a_resumed_runs_soak_counts_run_time_and_reads_memory_growth_in_the_last_of_equal_sessions():
    # session 1: 4 h, the learner leaking 30 MB/h and the log growing 50 MB/h; 10 h with nothing running; then
    # a resumed session of 4 h, its new learner flat after its first 2 h, the log growing on at 50 MB/h
    first = rows(4, lambda hour: 500.0 + 30 * hour, lambda hour: 50.0 * hour)
    second = [{**row, "time": 3600.0 * (14 + hour), "restarts": 1, "rss_mb_learner": 400.0 + 100 * min(hour, 2),
               "bytes_log": int((200 + 50 * hour) * 2**20)} for hour, row in enumerate(rows(4, float, float))]
    for session in (first, second):
        for hour, row in enumerate(session):
            row["elapsed_s"] = 3600.0 * hour + 60  # the stack's time since it started
    summary = soak.summarize(first + second)
    assert (summary["sessions"], summary["hours"], summary["samples"]) == (2, pytest.approx(8 + 60 / 3600), 10)
    assert summary["folder_mb_per_hour"] == pytest.approx(50.0, rel=0.02)  # not diluted by the 10 h between
    assert summary["memory"]["learner"]["second_half_mb_per_hour"] == pytest.approx(0.0, abs=1e-9)
    assert summary["restarts"] == 2 + 1  # each stack's count, summed
    assert "in 2 sessions" in soak.summary_text(summary)
    assert soak.summarize(first)["sessions"] == 1


def test_memory_growth_is_read_in_the_longest_session_not_a_short_last_one():
    # 4 h with a flat learner, then a resume of 12 minutes whose fresh learner fills at 500 MB/h
    first = rows(4, lambda hour: 500.0, lambda hour: 0.0)
    for hour, row in enumerate(first):
        row["elapsed_s"] = 3600.0 * hour + 60
    short = [{**first[0], "time": 3600.0 * 10 + 360 * tenth, "elapsed_s": 60.0 + 360 * tenth,
              "rss_mb_learner": 300.0 + 50 * tenth} for tenth in range(3)]
    summary = soak.summarize(first + short)
    assert (summary["sessions"], summary["growth_session"]) == (2, 0)
    assert summary["growth_session_hours"] == pytest.approx(4.0)
    assert summary["memory"]["learner"]["second_half_mb_per_hour"] == pytest.approx(0.0, abs=1e-9)
    assert "of session 1, the longest (4.00 h)" in soak.summary_text(summary)


def held_episode(seq: int, steps: int) -> StoredEpisode:
    frames = np.random.default_rng(seq).integers(0, 256, (steps + 1, 8, 8, 3), dtype=np.uint8)
    return StoredEpisode.of(FrameStack.from_array(frames), np.zeros(steps, np.int64), np.zeros(steps, np.float32),
                            np.zeros(steps, np.int64), False, seq=seq)


def test_a_sample_reads_the_bytes_of_the_episodes_the_replays_snapshot_holds(tmp_path):
    run = RunDir(tmp_path / "run")
    run.root.mkdir()
    RunStatus("finished", pids={}).write(run.status)
    assert soak.sample(run, RunStatus.read(run.status))["bytes_replay_held"] == ""  # no snapshot yet
    episodes = [held_episode(seq, steps) for seq, steps in enumerate((5, 9))]
    Snapshotter(run.replay_snapshot).write(SnapshotView(episodes, {}, {}, {}))
    held = soak.sample(run, RunStatus.read(run.status))["bytes_replay_held"]
    # each record: the episode's bytes and the msgpack fields around them (frame shape, flags, numbers)
    assert sum(episode.nbytes for episode in episodes) < held < sum(episode.nbytes for episode in episodes) + 400
    assert manifest_held(run.replay_snapshot) == (2, held)
    (run.replay_snapshot / MANIFEST).write_bytes(b"\x93 not a manifest")
    assert manifest_held(run.replay_snapshot) is None


def test_the_summary_separates_the_replays_growth_from_that_of_its_episodes():
    # the replay's memory grows 90 MB an hour while its episodes (lengthening) grow 80: 10 MB an hour is the rest
    held_rows = [{**row, "rss_mb_replay": 300.0 + 90 * hour, "bytes_replay_held": int((100 + 80 * hour) * 2**20)}
                 for hour, row in enumerate(rows(4, lambda hour: 500.0, lambda hour: 0.0))]
    held_rows[0]["bytes_replay_held"] = ""  # no snapshot yet at the first sample
    held = soak.summarize(held_rows)["replay_held"]
    assert (held["first_mb"], held["last_mb"]) == (180.0, 420.0)
    assert held["second_half_mb_per_hour"] == pytest.approx(80.0)
    assert held["replay_rest_mb_per_hour"] == pytest.approx(10.0)
    assert "the replay's memory less them: +10.0 MB/h" in soak.summary_text(soak.summarize(held_rows))
    assert soak.summarize(rows(4, lambda hour: 500.0, lambda hour: 0.0))["replay_held"] is None  # an older soak


def test_a_sample_reads_the_curves_follower_with_its_workers(tmp_path):
    run = RunDir(tmp_path / "run")
    run.root.mkdir()
    sleep = "import subprocess, sys, time; subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)']); " \
            "time.sleep(60)"
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)", "--curve", str(tmp_path / "x")])
    follower = subprocess.Popen([sys.executable, "-c", sleep, "--curve", "run"], cwd=tmp_path)  # relative to its cwd
    try:
        deadline = time.monotonic() + 30
        while len(soak.children(follower.pid)) < 1 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert soak.curve_followers(run) == [follower.pid]
        alone = soak.resident_mb(follower.pid)
        assert soak.tree_resident_mb([follower.pid]) > alone + 1  # and its worker
        row = soak.sample(run, RunStatus("training", pids={"learner": os.getpid()}))
        assert row["rss_mb_curve"] > alone
    finally:
        for process in (other, follower):
            for pid in soak.children(process.pid):
                os.kill(pid, 9)
            process.kill()
            process.wait()
    assert math.isnan(soak.tree_resident_mb(soak.curve_followers(run)))


def test_a_row_with_a_new_column_extends_the_files_header(tmp_path):
    path = tmp_path / "soak.csv"
    soak.append(path, {"time": 1.0, "rss_mb_learner": 500.0})
    soak.append(path, {"time": 2.0, "rss_mb_learner": 501.0, "rss_mb_curve": 300.0})
    assert list(csv.DictReader(path.open())) == [{"time": "1.0", "rss_mb_learner": "500.0", "rss_mb_curve": ""},
                                                 {"time": "2.0", "rss_mb_learner": "501.0", "rss_mb_curve": "300.0"}]


def test_a_soak_stopped_with_its_stack_reports_what_it_has_without_a_traceback(tmp_path, monkeypatch, capsys):
    def interrupted(run, every_s, until_s, stop, console):
        raise KeyboardInterrupt  # Ctrl-C (or the grid runner's stop) reaches the whole process group

    reported = []
    monkeypatch.setattr(soak, "watch", interrupted)
    monkeypatch.setattr(soak, "report", lambda run, console: reported.append(run))
    run = RunDir(tmp_path / "run")
    run.soak.mkdir(parents=True)
    (run.soak / "soak.csv").write_text("time\n1.0\n")
    assert soak.main([str(run.root)]) == 0
    assert reported and "soak: stopped" in capsys.readouterr().err


def test_a_steps_peak_is_the_most_its_process_trees_held_at_once(tmp_path):
    """A child holding 200 MB: the peak over the step reads it, though the child has ended by the stop."""
    hold = "import time; block = bytearray(b'1') * 200_000_000; time.sleep(1.5)"
    child = subprocess.Popen([sys.executable, "-c", hold])
    peak = soak.TreePeak(lambda: [child.pid] if child.poll() is None else [], every_s=0.05).start()
    child.wait()
    assert 200 < peak.stop() < 400
    assert math.isnan(soak.TreePeak(lambda: [], every_s=0.05).start().stop())  # nothing sampled


def test_a_child_started_from_a_thread_is_counted_in_its_parents_tree():
    """/proc lists a child under the thread that started it: the tree reads every thread's."""
    script = ("import subprocess, sys, threading, time\n"
              "def start():\n"
              "    subprocess.Popen([sys.executable, '-c', 'import time; b = bytearray(b\"1\") * 150_000_000; "
              "time.sleep(30)'])\n"
              "    time.sleep(30)  # the thread lives on: a child of an ended thread passes to the main one\n"
              "threading.Thread(target=start).start()\n"
              "time.sleep(30)\n")
    parent = subprocess.Popen([sys.executable, "-c", script])
    try:
        deadline = time.monotonic() + 20
        while soak.tree_resident_mb([parent.pid]) < 150 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert soak.tree_resident_mb([parent.pid]) > 150
    finally:
        for child in soak.children(parent.pid):
            os.kill(child, 9)
        parent.kill()
        parent.wait()


# A grid runner that starts the soak beside a run (deploy/grid/child_process.Child, as grid_job does), says its pid, waits.
RUNNER = """
import sys, time
from pathlib import Path
from deploy.grid.child_process import Child
run = Path(sys.argv[1])
child = Child([sys.executable, "deploy/labs/soak.py", str(run), "--every", "0.5"], run / "soak.log", None, None)
print(child.process.pid, flush=True)
time.sleep(120)
"""


def test_a_soak_whose_grid_runner_is_killed_reports_and_stops(tmp_path):
    """Its stack still says it trains (here: this test's pid); the soak stops because its runner is gone."""
    run = RunDir(tmp_path / "run")
    run.root.mkdir()
    RunStatus("training", pids={"learner": os.getpid()}).write(run.status)
    runner = subprocess.Popen([sys.executable, "-c", RUNNER, str(run.root)], cwd=Path(soak.__file__).parents[2],
                              stdout=subprocess.PIPE, text=True)
    sampler = None
    try:
        sampler = int(runner.stdout.readline())
        wait_for(lambda: (run.soak / "soak.csv").exists(), "the soak's first sample", 60)
        runner.kill()
        runner.wait(10)
        wait_for(lambda: not alive(sampler), "the soak to stop after its runner", 30)
        assert (run.soak / "soak_summary.md").exists()  # it reported what it had first
    finally:
        runner.kill()
        runner.stdout.close()
        if sampler is not None and alive(sampler):
            os.kill(sampler, 9)
