"""The README's "Running the processes by hand", run as written: its commands, read from the README,
with smoke-sized settings and a free loopback port. Only the learner is given a strategy (VDBE); the
actors must act with the learner's strategy and epsilon, not their default's, nor at random."""

import re
import shlex
import threading
import time
from pathlib import Path

from common.transport import subscribe
from common.keys import Keys
from common.wire.messages import EpisodeRecord, ExplorationState, flat_values
from common.wire.metrics import LearnerStats
from tests.processes import loopback_endpoint, router_client, start, stop

README = Path(__file__).resolve().parents[1] / "README.md"
README_ENDPOINT = "tcp/127.0.0.1:7447"
MODULES = {"replay": "replay.main", "learner": "learner.main", "actor": "actor.main"}
SMOKE = ["--preset", "smoke", "--network.lstm_units", "16"]  # smoke-sized, and a small LSTM for speed
DEADLINE_S = 180.0


def by_hand_commands() -> list[list[str]]:
    """The command lines of the first bash block under '## Running the processes by hand'."""
    section = README.read_text().split("## Running the processes by hand", 1)[1]
    block = re.search(r"```bash\n(.*?)```", section, re.S).group(1)
    return [shlex.split(line) for line in block.splitlines() if line.strip() and not line.startswith("#")]


def test_the_readme_example_trains_with_the_learners_strategy(tmp_path):
    commands = by_hand_commands()
    assert [command[0] for command in commands] == ["replay", "learner", "actor", "actor"]
    assert any("--exploration.strategy" in command for command in commands)  # the learner's
    endpoint = loopback_endpoint()
    run = next(command[command.index("--run.name") + 1] for command in commands)
    records: list[EpisodeRecord] = []
    states: list[ExplorationState] = []
    learner: list[dict] = []
    lock = threading.Lock()

    def on_metric(message, key):
        with lock:
            if isinstance(message, EpisodeRecord):
                records.append(message)
            elif isinstance(message, LearnerStats):
                learner.append(flat_values(message))

    def on_exploration(message, key):
        with lock:
            states.append(message)

    processes, logs = [], []
    session = None
    subscriptions = []
    try:
        for index, (role, *flags) in enumerate(commands):
            flags = [endpoint if flag == README_ENDPOINT else flag for flag in flags]
            logs.append(tmp_path / f"{index}-{role}.log")
            processes.append(start(["-m", MODULES[role], *flags, *SMOKE, "--run.runs_dir", str(tmp_path / "runs")],
                                   logs[-1]))
            if role == "replay":
                session = router_client(endpoint)
                keys = Keys("d3rqn", run)
                subscriptions = [subscribe(session, keys.metrics_all, on_metric),
                                 subscribe(session, keys.exploration, on_exploration, expected=ExplorationState)]

        def trained() -> bool:
            with lock:
                learned = {state.epsilon for state in states if state.strategy == "vdbe" and state.started}
                acted = {r.actor_id for r in records if r.weights_version >= 1 and r.epsilon in learned}
                return acted == {0, 1} and any(values["updates"] >= 5 for values in learner)

        deadline = time.monotonic() + DEADLINE_S
        while not trained():
            assert time.monotonic() < deadline, "\n".join(f"--- {p.name}\n{p.read_text()[-2500:]}" for p in logs)
            assert all(process.poll() is None for process in processes), \
                "\n".join(f"--- {p.name}\n{p.read_text()[-2500:]}" for p in logs)
            time.sleep(0.2)
    finally:
        stop(*processes)
        for subscription in subscriptions:
            subscription.undeclare()
        if session is not None:
            session.close()
    with lock:
        assert {state.strategy for state in states} == {"vdbe"}
        late = [r for r in records if r.weights_version >= 1]
        assert late and all(r.epsilon < 1.0 for r in late)  # VDBE's epsilon has moved; never random play
    for log in logs[2:]:  # each actor says once that it follows the learner, and never ignores its state
        text = log.read_text()
        assert text.count("following the learner's exploration: vdbe") == 1, text[-2000:]
        assert "this actor's config names bmc" in text and "ignoring" not in text
