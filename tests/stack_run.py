"""A local stack (deploy/launcher/stack.py) under test: started small, watched over Zenoh, stopped by itself.

    with StackRun(tmp_path, "name", actors=2) as run:
        run.wait(lambda w: w.updates() >= 5, "updates")
        ...
    run.summary()  # summary.json, after the stack stopped
"""

from __future__ import annotations

import hashlib
import json
import signal
import subprocess
import sys
import threading
import time
from collections import defaultdict
from pathlib import Path

from common.config import TransportConfig
from common.transport import open_session, subscribe
from common.keys import Keys
from common.wire.messages import Episode, EpisodeRecord, ReplayStats, flat_values
from common.wire.metrics import ActorStats, LearnerStats
from tests.processes import children, free_port, kill_tree

STACK = Path(__file__).resolve().parents[1] / "deploy" / "launcher" / "stack.py"
# Small and quick on a shared 2-core machine: a small LSTM, 2 traces of 5 steps, one torch thread.
SMALL = ["--preset", "smoke", "--network.lstm_units", "16", "--learner.batch_size", "2",
         "--learner.trace_length", "5", "--learner.n_mask", "2", "--learner.torch_threads", "1",
         "--pace.total_env_steps", "1000000", "--replay.stats_period_s", "0.5"]


def episode_digest(blobs, actions, rewards) -> str:
    digest = hashlib.sha1()
    for blob in blobs:
        digest.update(blob)
    digest.update(bytes(memoryview(actions.astype("<i8"))))
    digest.update(bytes(memoryview(rewards.astype("<f4"))))
    return digest.hexdigest()


class Watcher:
    """What the test sees of the run on Zenoh: the latest stats of each role, records and episodes."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.replay: dict = {}
        self.learner: dict = {}
        self.actor_stats: dict[str, dict] = {}
        self.records: dict[int, int] = defaultdict(int)  # actor id -> EpisodeRecords seen
        self.episodes: dict[str, Episode] = {}  # digest -> an episode an actor of the stack sent
        self.actor_ids: set[int] = set()

    def on_metric(self, message, key: str) -> None:
        with self.lock:
            if isinstance(message, EpisodeRecord) and message.actor_id in self.actor_ids:
                self.records[message.actor_id] += 1
            elif isinstance(message, LearnerStats) and key.endswith("/metrics/learner/0"):
                self.learner = flat_values(message)
            elif isinstance(message, ActorStats) and "/metrics/actor_stats/" in key:
                self.actor_stats[key.rsplit("/", 1)[1]] = flat_values(message)

    def on_replay(self, message, key: str) -> None:
        if isinstance(message, ReplayStats):
            with self.lock:
                self.replay = flat_values(message)

    def on_episode(self, message, key: str) -> None:
        if isinstance(message, Episode) and message.actor_id in self.actor_ids:
            digest = episode_digest(message.observations.blobs, message.actions, message.rewards)
            with self.lock:
                self.episodes[digest] = message

    def updates(self) -> int:
        return int(self.learner.get("updates", 0))


class StackRun:
    def __init__(self, tmp_path: Path, name: str, actors: int = 1, flags: tuple[str, ...] = ()) -> None:
        self.tmp_path = tmp_path
        self.name = name
        self.run_dir = tmp_path / name
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        self.keys = Keys("d3rqn", name)
        self.out_path = tmp_path / "stack.out"
        self.command = [sys.executable, str(STACK), *SMALL, "--actors", str(actors), "--port", str(self.port),
                        "--run.runs_dir", str(tmp_path), "--run.name", name, *flags]
        self.watch = Watcher()
        self.watch.actor_ids = set(range(actors))
        self.stack: subprocess.Popen | None = None
        self.session = None
        self._subscriptions = []

    def __enter__(self) -> StackRun:
        self.stack = subprocess.Popen(self.command, stdout=open(self.out_path, "wb"), stderr=subprocess.STDOUT,
                                      cwd=self.tmp_path)
        try:
            self.session = open_session(TransportConfig(mode="client", connect=[self.endpoint],
                                                        connect_timeout_s=60.0))
            self._subscriptions = [subscribe(self.session, self.keys.metrics_all, self.watch.on_metric),
                                   subscribe(self.session, self.keys.replay_stats, self.watch.on_replay),
                                   subscribe(self.session, self.keys.episodes, self.watch.on_episode)]
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc_info) -> None:
        try:
            self.stop()
        finally:
            for subscription in self._subscriptions:
                subscription.undeclare()
            if self.session is not None:
                self.session.close()

    def stop(self, timeout_s: float = 90.0) -> int:
        """Ctrl-C to the stack (it stops its processes in order); kills what is left if it hangs."""
        stack = self.stack
        if stack is None or stack.poll() is not None:
            return stack.returncode if stack is not None else 0
        stack.send_signal(signal.SIGINT)
        try:
            return stack.wait(timeout_s)
        except subprocess.TimeoutExpired:
            kill_tree(stack)
            raise AssertionError(f"the stack did not stop within {timeout_s:.0f}s\n{self.logs()}")

    def roles(self) -> dict[str, int]:
        """Role name (replay, learner, recorder, actor-<id>) -> pid of the stack's children now."""
        found = {}
        for pid, command in children(self.stack.pid).items():
            words = command.split()
            module = words[2] if len(words) > 2 else ""
            if module == "actor.main":
                found[f"actor-{words[words.index('--actor.actor_id') + 1]}"] = pid
            elif module == "replay.recorder.cli":
                found["recorder"] = pid
            elif module in ("replay.main", "learner.main"):
                found[module.split(".")[0]] = pid
        return found

    def wait(self, condition, what: str, timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self.watch.lock:
                if condition(self.watch):
                    return
            if self.stack.poll() is not None:
                raise AssertionError(f"the stack exited while waiting for {what}\n{self.logs()}")
            time.sleep(0.2)
        raise AssertionError(f"timed out after {timeout_s:.0f}s waiting for {what}\n{self.logs()}")

    def logs(self) -> str:
        paths = [self.out_path, *sorted((self.run_dir / "logs").glob("*.log"))]
        return "\n".join(f"--- {path.name}\n{path.read_text(errors='replace')[-2500:]}" for path in paths
                         if path.exists())

    def summary(self) -> dict:
        return json.loads((self.run_dir / "summary.json").read_text())
