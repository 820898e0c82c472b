"""The across-machines set-up of deploy/configs, played on loopback.

A hub replay (router) for run "cluster", a second run's replay sharing the same
router, and an actor started from the remote-actor config: the actor's episodes
reach its own run's replay and nothing leaks into the other run.
"""

import subprocess
import threading
import time
from pathlib import Path

import pytest

from common.config import TransportConfig
from common.config_values import load_config
from common.transport import open_session, subscribe
from common.keys import Keys
from common.wire.messages import ReplayStats, flat_values
from tests.processes import loopback_endpoint, start, stop

CONFIGS = Path(__file__).resolve().parents[1] / "deploy" / "configs"
EPISODES = 3
ROUTER_WAIT_S = 60.0


@pytest.mark.parametrize("name", ["hub-replay.toml", "hub-learner.toml", "remote-actor.toml"])
def test_deploy_configs_are_valid(name):
    config = load_config("paper", CONFIGS / name)
    assert config.run.name == "cluster"
    assert config.transport.mode in ("router", "client")


def test_actor_on_another_host_feeds_only_its_own_run(tmp_path):
    endpoint = loopback_endpoint()
    processes = []

    def start_logged(name: str, *flags: str) -> subprocess.Popen:
        process = start(["-m", *flags], tmp_path / f"{name}.log")
        processes.append(process)
        return process

    # a loaded machine starts the hub's router slowly: the clients wait for it as the stack's own session does
    fast_stats = ("--replay.stats_period_s", "0.2", "--run.runs_dir", str(tmp_path / "runs"),
                  "--transport.connect_timeout_s", str(ROUTER_WAIT_S))
    start_logged("hub", "replay.main", "--config", str(CONFIGS / "hub-replay.toml"), "--transport.listen", endpoint,
          *fast_stats)
    start_logged("other", "replay.main", "--run.name", "other", "--transport.mode", "client",
          "--transport.connect", endpoint, *fast_stats)
    latest: dict[str, dict] = {}
    lock = threading.Lock()

    def keep(run: str):
        def on_stats(message, key):
            with lock:
                latest[run] = flat_values(message)
        return on_stats

    session, subscriptions = None, []
    try:  # from here on the replays stop whatever fails, the session's opening too
        session = open_session(TransportConfig(mode="client", connect=[endpoint], connect_timeout_s=ROUTER_WAIT_S))
        subscriptions = [subscribe(session, Keys("d3rqn", run).replay_stats, keep(run), expected=ReplayStats)
                         for run in ("cluster", "other")]
        actor = start_logged("actor", "actor.main", "--config", str(CONFIGS / "remote-actor.toml"),
                      "--transport.connect", endpoint, "--transport.connect_timeout_s", str(ROUTER_WAIT_S),
                      "--actor.actor_id", "7", "--env.max_steps", "50",
                      "--max-episodes", str(EPISODES))
        assert actor.wait(120) == 0, (tmp_path / "actor.log").read_text()
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            with lock:
                hub = latest.get("cluster", {})
                if hub.get("inserted", 0) + hub.get("short_dropped", 0) == EPISODES and "other" in latest:
                    break
            time.sleep(0.1)
        with lock:
            assert latest["cluster"]["inserted"] + latest["cluster"]["short_dropped"] == EPISODES
            assert latest["other"]["inserted"] + latest["other"]["short_dropped"] == 0
    finally:
        for subscription in subscriptions:
            subscription.undeclare()
        if session is not None:
            session.close()
        stop(*processes)
