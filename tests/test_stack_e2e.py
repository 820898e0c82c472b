"""End to end: replay + learner + 2 actors as real processes over loopback Zenoh."""

import math
import os
import subprocess
import threading
import time
from collections import defaultdict

import pytest

from common.presets import PRESETS
from common.transport import subscribe
from common.keys import Keys
from common.wire.messages import EpisodeRecord, ExplorationState, flat_values
from common.wire.metrics import LearnerStats
from tests.processes import loopback_endpoint, router_client, start, stop

DEADLINE_S = 240.0
SMOKE_CAPACITY = PRESETS["smoke"]["replay.capacity"]


class Observer:
    """What the test sees of the run on Zenoh."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.records = defaultdict(list)  # actor id -> EpisodeRecords
        self.replay: list[dict] = []
        self.learner: list[dict] = []
        self.exploration: list[ExplorationState] = []

    def on_metric(self, message, key):
        with self.lock:
            if isinstance(message, EpisodeRecord):
                self.records[message.actor_id].append(message)
            elif isinstance(message, LearnerStats):
                self.learner.append(flat_values(message))

    def on_replay(self, message, key):
        with self.lock:
            self.replay.append(flat_values(message))

    def on_exploration(self, message, key):
        with self.lock:
            self.exploration.append(message)

    def wait_for(self, condition, what: str, deadline: float) -> None:
        while time.monotonic() < deadline:
            with self.lock:
                if condition(self):
                    return
            time.sleep(0.2)
        raise AssertionError(f"timed out waiting for {what}")


def start_role(role: str, flags: list[str], log_dir) -> subprocess.Popen:
    return start(["-m", f"{role}.main", *flags], log_dir / f"{role}-{len(list(log_dir.iterdir()))}.log")


@pytest.fixture
def stack(tmp_path):
    endpoint = loopback_endpoint()
    run = f"e2e{os.getpid()}"
    common = ["--preset", "smoke", "--run.name", run, "--run.runs_dir", str(tmp_path / "runs"),
              "--exploration.strategy", "bmc"]
    client = common + ["--transport.mode", "client", "--transport.connect", endpoint]
    logs = tmp_path / "logs"
    logs.mkdir()
    processes = {"replay": start_role("replay", common + ["--transport.mode", "router", "--transport.listen", endpoint], logs)}
    observer = Observer()
    session = router_client(endpoint)
    keys = Keys("d3rqn", run)
    subscriptions = [subscribe(session, keys.metrics_all, observer.on_metric),
                     subscribe(session, keys.replay_stats, observer.on_replay),
                     subscribe(session, keys.exploration, observer.on_exploration)]
    processes["learner"] = start_role("learner", client + ["--pace.total_env_steps", "100000"], logs)
    for actor_id in (0, 1):
        processes[f"actor{actor_id}"] = start_role("actor", client + ["--actor.actor_id", str(actor_id)], logs)
    try:
        yield processes, observer, logs
    finally:
        stop(*processes.values())
        for subscription in subscriptions:
            subscription.undeclare()
        session.close()


def dump_logs(logs) -> str:
    return "\n".join(f"--- {path.name}\n{path.read_text()[-3000:]}" for path in sorted(logs.iterdir()))


def test_replay_learner_and_two_actors_train_together(stack):
    processes, observer, logs = stack
    deadline = time.monotonic() + DEADLINE_S
    try:
        observer.wait_for(lambda o: o.replay and o.replay[-1]["episodes"] >= 2, "episodes in the replay", deadline)
        observer.wait_for(lambda o: any(v["updates"] >= 3 for v in o.learner), "learner updates", deadline)
        observer.wait_for(lambda o: o.replay[-1]["traces_served"] > 0, "batches served", deadline)
        observer.wait_for(lambda o: any(s.started for s in o.exploration), "exploration state", deadline)
        observer.wait_for(lambda o: all(any(r.weights_version >= 1 and r.epsilon < 1.0 for r in o.records[a])
                                        for a in (0, 1)), "actors acting with new weights", deadline)
    except AssertionError:
        raise AssertionError(dump_logs(logs)) from None
    with observer.lock:
        losses = [v["loss"] for v in observer.learner if v["updates"] > 0]
    assert losses and all(math.isfinite(loss) for loss in losses)
    with observer.lock:  # the learner states its start rule for the replay (BMC: by episodes)
        assert observer.exploration and all(s.start_by_steps is False for s in observer.exploration)

    # SIGKILL one actor: the other goes on and the replay loses nothing it stored.
    processes["actor0"].kill()
    processes["actor0"].wait()
    with observer.lock:
        stored_before = observer.replay[-1]["episodes"]
        inserted_before = observer.replay[-1]["inserted"]
        episodes_of_survivor = len(observer.records[1])
    observer.wait_for(lambda o: len(o.records[1]) >= episodes_of_survivor + 2, "the surviving actor's episodes",
                      deadline)
    observer.wait_for(lambda o: o.replay[-1]["inserted"] > inserted_before, "new inserts", deadline)
    with observer.lock:
        latest = observer.replay[-1]
        assert latest["episodes"] >= stored_before or latest["episodes"] == SMOKE_CAPACITY
        assert latest["episodes"] == min(latest["inserted"], SMOKE_CAPACITY)  # nothing lost but by eviction
        assert latest["rejected_messages"] == 0
    for name in ("replay", "learner", "actor1"):
        assert processes[name].poll() is None, f"{name} died\n{dump_logs(logs)}"
