"""The local stack, the main job: replay + learner + N actors on this machine over loopback.

Each role runs as its own process (a fresh interpreter, never a fork holding a
Zenoh session). The replay opens its session as the router that the others
connect to. This launcher shows one live progress line, writes everything for
the run under <runs_dir>/<run>/, restarts an actor that dies, and stops every
process on Ctrl-C or when the learner reaches its step budget. At the end it
writes <runs_dir>/<run>/summary.json: env steps, updates and the achieved env
steps per update of the whole run, from the learner's last metrics.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections import deque
from pathlib import Path

from common.config import Config, add_config_arguments, parse_config_or_exit, to_toml
from common.transport import Keys, open_session, subscribe
from common.wire import EpisodeRecord, Stats

STOP_GRACE_S = 20.0
RESTART_BACKOFF_S = 2.0
FINAL_METRICS_WAIT_S = 5.0
SUMMARY = "summary.json"


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def default_actor_count() -> int:
    """One actor per core the learner does not use."""
    return max(1, (os.cpu_count() or 2) - 1)


class Progress:
    """Collects the system's metrics from Zenoh and renders the live progress line."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.returns: deque[float] = deque(maxlen=100)
        self.episodes = 0
        self.replay: dict = {}
        self.learner: dict = {}
        self.learner_final = threading.Event()  # the learner's last metrics, sent as it stops
        self._started = time.monotonic()

    def on_metric(self, message, key: str) -> None:
        with self._lock:
            if isinstance(message, EpisodeRecord):
                self.episodes += 1
                self.returns.append(message.episode_return)
            elif isinstance(message, Stats) and message.source == "learner":
                self.learner = dict(message.values)
                if self.learner.get("final"):
                    self.learner_final.set()

    def on_replay_stats(self, message, key: str) -> None:
        if isinstance(message, Stats):
            with self._lock:
                self.replay = dict(message.values)

    def line(self) -> str:
        with self._lock:
            mean_return = sum(self.returns) / len(self.returns) if self.returns else float("nan")
            steps = int(self.replay.get("env_steps_total", 0))
            elapsed = time.monotonic() - self._started
            return (f"[{elapsed:7.0f}s] env steps {steps:>9,d} | episodes {self.episodes:>6,d} | "
                    f"updates {int(self.learner.get('updates', 0)):>7,d} | "
                    f"eps {float(self.learner.get('epsilon', 1.0)):.3f} | "
                    f"return(100) {mean_return:8.2f} | "
                    f"upd/s {float(self.learner.get('updates_per_s', 0.0)):5.2f} | "
                    f"steps/s {float(self.replay.get('env_steps_total_per_s', 0.0)):6.1f} | "
                    f"steps/upd {float(self.learner.get('env_steps_per_update', math.nan)):5.2f}")

    def summary(self, config: Config) -> dict:
        """The run's figures from the learner's last metrics (and the replay's last stats)."""
        with self._lock:
            learner, replay = dict(self.learner), dict(self.replay)
        return {
            "run": config.run.name,
            "strategy": config.exploration.strategy,
            "learner_finished": bool(learner.get("final")),
            "updates": int(learner.get("updates", 0)),
            "env_steps": int(learner.get("env_steps", 0)),
            "start_env_steps": learner.get("start_env_steps"),
            "env_steps_per_update": learner.get("env_steps_per_update"),  # achieved, since the start mark
            "env_steps_per_update_configured": config.learner.env_steps_per_update,
            "replay_env_steps_total": int(replay.get("env_steps_total", 0)),
            "episodes": self.episodes,
        }


class Stack:
    """Starts, watches and stops the processes of one local run."""

    def __init__(self, config: Config, config_path: Path, run_dir: Path, endpoint: str,
                 actors: int, resume: bool) -> None:
        self.config = config
        self.run_dir = run_dir
        self.logs = run_dir / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        self.base = ["--config", str(config_path)]
        self.endpoint = endpoint
        self.actor_count = actors
        self.resume = resume
        self.processes: dict[str, subprocess.Popen] = {}
        self.restarts = 0

    def start_all(self) -> None:
        resume = ["--resume"] if self.resume else []  # the replay's rate limiter counters, the learner's checkpoint
        self._start("replay", "replay.main", ["--transport.mode", "router", "--transport.listen", self.endpoint] + resume)
        if self.config.record.enabled:  # the flight recorder writes <run dir>/traffic.mcap
            self._start("recorder", "replay.log.cli record", self._client_flags())
        self._start("learner", "learner.main", self._client_flags() + resume)
        for actor_id in range(self.actor_count):
            self._start_actor(actor_id)

    def watch(self, stop: threading.Event, progress: Progress) -> int:
        """Returns the learner's exit code; restarts dead actors meanwhile."""
        last_line = 0.0
        while not stop.is_set():
            learner_code = self.processes["learner"].poll()
            if learner_code is not None:
                return learner_code
            if self.processes["replay"].poll() is not None:
                print("\nreplay exited unexpectedly; stopping the stack (see logs/replay.log)", file=sys.stderr)
                return 1
            self._restart_dead_actors()
            if time.monotonic() - last_line >= 1.0:
                print("\r" + progress.line(), end="", flush=True)
                last_line = time.monotonic()
            stop.wait(0.2)
        return 0

    def stop_all(self) -> None:
        """Learner first (it checkpoints), then actors, the recorder (it has seen their last messages), replay last."""
        order = (["learner"] + sorted(name for name in self.processes if name.startswith("actor"))
                 + ["recorder", "replay"])
        for name in order:
            process = self.processes.get(name)
            if process is not None and process.poll() is None:
                process.send_signal(signal.SIGINT)
                try:
                    process.wait(STOP_GRACE_S)
                except subprocess.TimeoutExpired:
                    print(f"\n{name} did not stop within {STOP_GRACE_S:.0f}s; killing it", file=sys.stderr)
                    process.kill()
                    process.wait()

    def _client_flags(self) -> list[str]:
        return ["--transport.mode", "client", "--transport.connect", self.endpoint]

    def _start_actor(self, actor_id: int) -> None:
        self._start(f"actor-{actor_id}", "actor.main", self._client_flags() + ["--actor.actor_id", str(actor_id)])

    def _start(self, name: str, module: str, flags: list[str]) -> None:
        log = open(self.logs / f"{name}.log", "ab")
        command = [sys.executable, "-m", *module.split(), *self.base, *flags]  # module, then any subcommand
        self.processes[name] = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT,
                                                stdin=subprocess.DEVNULL, start_new_session=True)
        log.close()

    def _restart_dead_actors(self) -> None:
        for name, process in list(self.processes.items()):
            if name.startswith("actor-") and process.poll() is not None:
                print(f"\n{name} exited with code {process.returncode}; restarting it", file=sys.stderr)
                self.restarts += 1
                time.sleep(RESTART_BACKOFF_S)
                self._start_actor(int(name.split("-")[1]))


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="deploy/run.sh",
        description="Run the whole system locally: replay + learner + actors over loopback Zenoh. "
                    "Everything for the run goes to <run.runs_dir>/<run.name>/.")
    parser.add_argument("--actors", type=int, default=None,
                        help="number of actors (default: actor.num_actors, or one per spare core)")
    parser.add_argument("--port", type=int, default=0, help="loopback port of the replay's router (default: a free one)")
    parser.add_argument("--resume", action="store_true", help="resume the learner from the run's latest checkpoint")
    add_config_arguments(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    args, config = parse_config_or_exit(build_parser(), argv)
    run_dir = Path(config.run.runs_dir) / config.run.name
    run_dir.mkdir(parents=True, exist_ok=True)
    config_path = run_dir / "config.toml"
    config_path.write_text(to_toml(config))
    endpoint = f"tcp/127.0.0.1:{args.port or free_port()}"
    actors = args.actors or config.actor.num_actors or default_actor_count()
    print(f"run {config.run.name!r}: strategy {config.exploration.strategy}, {actors} actor(s), "
          f"router {endpoint}, files in {run_dir}/", flush=True)

    stack = Stack(config, config_path, run_dir, endpoint, actors, args.resume)
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    progress = Progress()
    stack.start_all()
    watcher_config = config.transport
    watcher_config.mode, watcher_config.connect, watcher_config.listen = "client", [endpoint], []
    session = open_session(watcher_config)
    keys = Keys(config.transport.namespace, config.run.name)
    subscriptions = [subscribe(session, keys.metrics_all, progress.on_metric),
                     subscribe(session, keys.replay_stats, progress.on_replay_stats)]
    try:
        code = stack.watch(stop, progress)
        if stack.processes["learner"].poll() is not None:
            progress.learner_final.wait(FINAL_METRICS_WAIT_S)
    finally:
        print("\n" + progress.line(), flush=True)
        print("stopping processes ...", flush=True)
        stack.stop_all()
        for subscription in subscriptions:
            subscription.undeclare()
        session.close()
    summary = progress.summary(config)
    (run_dir / SUMMARY).write_text(json.dumps(summary, indent=2) + "\n")
    ratio = summary["env_steps_per_update"]
    shown = f"{ratio:.3f}" if isinstance(ratio, (int, float)) else "unknown"
    print(f"run: {summary['env_steps']:,d} env steps, {summary['updates']:,d} updates, {shown} env steps per "
          f"update (configured {config.learner.env_steps_per_update:g}); {run_dir / SUMMARY}", flush=True)
    print(f"stopped; actor restarts: {stack.restarts}; logs in {stack.logs}/", flush=True)
    return code


if __name__ == "__main__":
    sys.exit(main())
