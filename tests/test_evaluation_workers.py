"""Evaluation workers do not outlive their parent: killed, evaluate can read no episode, so its workers stop
instead of driving the rest of a queue that can hold hours of jobs."""

import os
import queue
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from actor.evaluation import episodes
from actor.evaluation.episodes import EpisodeJob, queued_jobs
from deploy.labs.soak import children
from tests.processes import alive
from tests.test_evaluation import make_checkpoint

ROOT = Path(__file__).resolve().parents[1]

# A parent that starts 2 workers on a long queue of random-policy episodes, says their pids, and waits.
PARENT = """
import multiprocessing
from actor.evaluation.episodes import episode_jobs
from actor.evaluation.status import EvaluationStatus
from actor.evaluation.workers import run_jobs
from common.config_values import load_config

class SayPids(EvaluationStatus):  # after 20 episodes the workers are driving: say who they are
    senders = 0
    def add(self, episode):
        super().add(episode)
        SayPids.senders += 1
        if SayPids.senders == 20:
            print(" ".join(str(child.pid) for child in multiprocessing.active_children()), flush=True)

config = load_config("smoke", overrides={"evaluation.workers": 2, "evaluation.envs_per_worker": 1,
                                         "evaluation.max_steps": 2000})
jobs = episode_jobs(["random"], ["train", "test"], 2000, 0)  # 40,000 episodes: far longer than the test
run_jobs(config, None, jobs, SayPids(len(jobs), 60.0, stream=None))
"""


def test_the_workers_stop_when_their_parent_is_killed():
    parent = subprocess.Popen([sys.executable, "-c", PARENT], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        workers = [int(pid) for pid in parent.stdout.readline().split()]
        assert len(workers) == 2 and all(alive(pid) for pid in workers)
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
        deadline = time.monotonic() + 30
        while any(alive(pid) for pid in workers) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(alive(pid) for pid in workers)
    finally:
        parent.kill()
        parent.stdout.close()
        for pid in workers if "workers" in locals() else []:
            if alive(pid):
                os.kill(pid, signal.SIGKILL)


class Jobs:
    """A job queue that never blocks: an empty get raises queue.Empty, as a multiprocessing queue's get with a
    timeout does, and calls on_empty first (the parent dying while the worker waits)."""

    def __init__(self, jobs, on_empty=None):
        self.jobs = list(jobs)
        self.on_empty = on_empty

    def get(self, timeout=None):
        assert timeout is not None, "a blocking get would wait forever on a queue whose parent is gone"
        if not self.jobs:
            if self.on_empty:
                self.on_empty()
            raise queue.Empty
        return self.jobs.pop(0)


def test_a_worker_takes_no_job_once_its_parent_is_gone():
    jobs = [EpisodeJob("random", "train", 0, trial, trial) for trial in range(3)] + [None]
    assert len(list(queued_jobs(Jobs(jobs), parent_pid=os.getppid()))) == 3
    assert list(queued_jobs(Jobs(jobs), parent_pid=os.getppid() + 100_000)) == []  # not its parent
    assert len(list(queued_jobs(Jobs(jobs)))) == 3  # no parent to watch


def test_a_worker_waiting_on_an_empty_queue_stops_when_its_parent_dies(monkeypatch):
    """A killed parent's end markers never reach the queue: the worker that empties it must not wait forever."""
    parent = os.getppid()
    monkeypatch.setattr(episodes.os, "getppid", lambda: parent)

    def parent_dies():
        monkeypatch.setattr(episodes.os, "getppid", lambda: 1)  # reparented

    jobs = [EpisodeJob("random", "train", 0, trial, trial) for trial in range(2)]  # no end marker
    assert len(list(queued_jobs(Jobs(jobs, on_empty=parent_dies), parent_pid=parent))) == 2


# A grid runner (deploy/grid/child_process.Child starts its stack and evaluate) that starts a long evaluate, says its pid,
# and waits.
RUNNER = """
import signal, sys, time
from pathlib import Path
if sys.argv[3] == "ignored":  # a runner started in the background of a script: SIGINT ignored, and so its children
    signal.signal(signal.SIGINT, signal.SIG_IGN)
from deploy.grid.child_process import Child
run_dir, out = sys.argv[1], Path(sys.argv[2])
child = Child([sys.executable, "-m", "actor.evaluation.command", "--checkpoint", run_dir, "--out", str(out / "evaluation"),
               "--evaluation.episodes_per_start", "200", "--evaluation.workers", "1"], out / "evaluate.log", None, None)
print(child.process.pid, flush=True)
time.sleep(300)
"""


@pytest.mark.parametrize("sigint", ["handled", "ignored"])
def test_an_evaluation_stops_when_the_grid_runner_that_started_it_is_killed(tmp_path, sigint):
    """A runner killed (SIGKILL, a crash) leaves no evaluation reading policies for nobody: Child hands it the
    runner's pid, and evaluate interrupts itself once that process is gone, as a Ctrl-C would (or exits, where
    it ignores SIGINT), and its workers stop with it."""
    run_dir = make_checkpoint(tmp_path / "runs")
    runner = subprocess.Popen([sys.executable, "-c", RUNNER, str(run_dir), str(tmp_path), sigint], cwd=ROOT,
                              stdout=subprocess.PIPE, text=True)
    evaluate, helpers = None, []
    try:
        evaluate = int(runner.stdout.readline())
        deadline = time.monotonic() + 60
        while len(children(evaluate)) < 2 and time.monotonic() < deadline:
            time.sleep(0.2)  # its worker and multiprocessing's resource tracker: it is evaluating
        helpers = children(evaluate)
        assert alive(evaluate) and len(helpers) == 2
        runner.send_signal(signal.SIGKILL)
        runner.wait(10)
        deadline = time.monotonic() + 30
        while any(alive(pid) for pid in [evaluate, *helpers]) and time.monotonic() < deadline:
            time.sleep(0.2)
        log = (tmp_path / "evaluate.log").read_text()[-2000:]  # (what it said last went to the runner, now gone)
        left = [Path(f"/proc/{pid}/cmdline").read_text().replace("\0", " ")[-120:]
                for pid in [evaluate, *helpers] if alive(pid)]
        assert not left, f"{left}; {log}"
    finally:
        runner.kill()
        runner.stdout.close()
        for pid in [evaluate, *helpers] if evaluate is not None else []:
            if alive(pid):
                os.kill(pid, signal.SIGKILL)
