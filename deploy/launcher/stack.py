"""The local stack, the main job: replay + learner + N actors on this machine over loopback.

Each role runs as its own process (a fresh interpreter, never a fork holding a
Zenoh session). The replay opens its session as the router that the others
connect to. This launcher writes everything for the run into its run folder
(common/run_dir.py), and stops every process on Ctrl-C or when the learner
reaches its step budget (it exits with code 0). Every second it rewrites the
run's status file (phase, env steps of the budget, updates, mean return, ETA,
restarts, pids; RunStatus) and, on a terminal, one live line with the
same figures.

A process that ends for a full disk (DISK_FULL_EXIT) is started again once the disk has room (DiskWatch), which
the live line shows. Any process that dies otherwise is started again after a backoff (RESTART_BACKOFF_S,
doubled for each death in a row up to RESTART_BACKOFF_MAX_S; a process that lived
STABLE_S starts from the first step again): the replay with --resume (its snapshot
and counters), the learner with --resume once it has a checkpoint, the recorder
(into a new numbered log) and actors as they were. The others ride it out: they
reconnect to a restarted replay on their own. The live line counts restarts,
and at the end the run's summary file gives env steps, updates and the achieved
env steps per update of the whole run, from the learner's last metrics, and the
restarts of each process.

One stack runs a run folder at a time (deploy/launcher/run_claim.py). A stack whose
output nobody reads any more (its reader killed, a terminal hung up) stops
the run cleanly as Ctrl-C does (deploy/launcher/console.py).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time

import zenoh

from common.atomic_file import remove_dead_temporaries, write_text_atomically
from common.config import Config
from common.config_cli import add_config_arguments, parse_config_or_exit
from common.config_values import to_toml
from common.cpu_capability import exit_if_unrunnable
from common.disk_space import DISK_FULL_EXIT, size_text
from common.run_dir import RunDir
from common.shell import env_stopping_with_this, on_stop_signals, run_main, stop_with_parent
from common.transport import free_port, open_session, subscribe
from common.keys import Keys
from deploy.launcher.console import Console
from deploy.launcher.disk_watch import DiskWatch
from deploy.launcher.stack_monitor import StackMonitor
from deploy.launcher.run_claim import RunClaimError, claim_run

STOP_GRACE_S = 20.0
RESTART_BACKOFF_S = 1.0  # the wait before restarting a process that died, doubled for each death in a row
RESTART_BACKOFF_MAX_S = 30.0
STABLE_S = 60.0  # a process that lived this long before dying is restarted after RESTART_BACKOFF_S again
FINAL_METRICS_WAIT_S = 5.0
WATCHER_CONNECT_S = 180.0  # how long the stack waits for its replay's router: a loaded machine starts it slowly
SPACE_POLL_S = 5.0  # how often the stack looks for room to start a process that ended for a full disk
STATUS_PERIOD_S = 1.0  # the status file and the live line
LOGGED_LINE_PERIOD_S = 30.0  # the live line, logged, when stdout is not a terminal


def default_actor_count() -> int:
    """One actor per core the learner does not use."""
    return max(1, (os.cpu_count() or 2) - 1)


class Role:
    """One process of the stack, how to start it, and its deaths."""

    def __init__(self, name: str, module: str, flags: list[str]) -> None:
        self.name = name
        self.module = module
        self.flags = flags
        self.process: subprocess.Popen | None = None
        self.started = 0.0
        self.restarts = 0
        self.deaths_in_a_row = 0
        self.restart_at: float | None = None  # set while waiting to be started again
        self.waits_for_space = False  # it ended for a full disk: started again once there is room

    def backoff_s(self) -> float:
        return min(RESTART_BACKOFF_S * 2 ** (self.deaths_in_a_row - 1), RESTART_BACKOFF_MAX_S)


class Stack:
    """Starts, watches, restarts and stops the processes of one local run."""

    def __init__(self, config: Config, run: RunDir, endpoint: str, actors: int, resume: bool,
                 tensorboard: bool = False, console: Console | None = None) -> None:
        self.config = config
        self.console = console or Console(threading.Event())
        self.run = run
        run.logs.mkdir(parents=True, exist_ok=True)
        self.base = ["--config", str(run.config)]
        self.endpoint = endpoint
        self.resume = resume  # the first start: the replay's snapshot and counters, the learner's checkpoint
        client = ["--transport.mode", "client", "--transport.connect", endpoint]
        self.roles: dict[str, Role] = {"replay": Role("replay", "replay.main", [
            "--transport.mode", "router", "--transport.listen", endpoint])}
        if config.recorder.enabled:  # the flight recorder writes the run's wire log
            curves = ["--tensorboard", str(run.tensorboard)] if tensorboard else []
            self.roles["recorder"] = Role("recorder", "replay.recorder.cli record", client + curves)
        self.roles["learner"] = Role("learner", "learner.main", client)
        self.learner_finished = False  # the learner exited by itself: the budget is paid for
        self.status_failed = False
        self.disk = DiskWatch(run, lambda line: self.console.say(f"\n{line}", err=True))
        for actor_id in range(actors):
            self.roles[f"actor-{actor_id}"] = Role(f"actor-{actor_id}", "actor.main",
                                                   client + ["--actor.actor_id", str(actor_id)])

    @property
    def processes(self) -> dict[str, subprocess.Popen]:
        return {name: role.process for name, role in self.roles.items() if role.process is not None}

    @property
    def restarts(self) -> dict[str, int]:
        return {name: role.restarts for name, role in self.roles.items()}

    @property
    def pids(self) -> dict[str, int]:
        return {name: process.pid for name, process in self.processes.items() if process.poll() is None}

    def report(self, monitor: StackMonitor, phase: str, line: str = "") -> None:
        """Rewrites the status file (a failure is said once; the run goes on) and prints the live line:
        ``line`` "live" rewrites it in place, "logged" prints it on a line of its own, "" not at all."""
        free = self.disk.look()
        try:
            monitor.status(phase, self.restarts, self.pids, free).write(self.run.status)
        except OSError as error:
            if not self.status_failed:
                self.console.say(f"\ncannot write the status file: {error}", err=True)
            self.status_failed = True
        if line:
            self.console.say("\r" if line == "live" else "", monitor.line(sum(self.restarts.values()), free),
                             end="" if line == "live" else "\n")

    def start_all(self) -> None:
        for role in self.roles.values():
            self._start(role, first=True)

    def watch(self, stop: threading.Event, monitor: StackMonitor) -> int:
        """Returns 0 once the learner has finished (exit code 0); restarts what dies meanwhile."""
        last_report = last_line = 0.0
        terminal = sys.stdout.isatty()
        while not stop.is_set():
            now = time.monotonic()
            for role in self.roles.values():
                code = role.process.poll() if role.restart_at is None else None
                if code == 0 and role.name == "learner":
                    self.learner_finished = True
                    return 0  # the budget is paid for: the run is over
                if code is not None:
                    self._died(role, code, now)
                elif role.restart_at is not None and now >= role.restart_at:
                    if role.waits_for_space and not self.disk.room_to_start():
                        role.restart_at = now + SPACE_POLL_S
                        continue
                    role.restart_at, role.waits_for_space = None, False
                    role.restarts += 1
                    self._start(role)
            if now - last_report >= STATUS_PERIOD_S and self.console.check():
                # A terminal gets the line rewritten in place; a pipe or file one line per period.
                line_due = terminal or now - last_line >= LOGGED_LINE_PERIOD_S
                self.report(monitor, "training", "live" if terminal else "logged" if line_due else "")
                last_report, last_line = now, now if line_due else last_line
            stop.wait(0.2)
        return 0

    def _died(self, role: Role, code: int, now: float) -> None:
        role.deaths_in_a_row = 1 if now - role.started >= STABLE_S else role.deaths_in_a_row + 1
        role.restart_at = now + role.backoff_s()
        if code == DISK_FULL_EXIT:  # restarted now, it would only die again: it waits for room
            role.waits_for_space = True
            self.console.say(f"\n{role.name} stopped: the disk of {self.run.root} is full "
                             f"({size_text(self.disk.free)} free); it starts again once there is room "
                             f"(see {self.run.log(role.name)})", err=True)
            return
        self.console.say(f"\n{role.name} exited with code {code}; restarting it in {role.backoff_s():.0f}s "
                         f"(see {self.run.log(role.name)})", err=True)

    def stop_all(self) -> None:
        """Learner first (it checkpoints), then actors, the recorder (it has seen their last messages), replay last."""
        order = (["learner"] + sorted(name for name in self.roles if name.startswith("actor"))
                 + ["recorder", "replay"])
        for name in order:
            role = self.roles.get(name)
            process = role.process if role is not None else None
            if process is not None and process.poll() is None:
                process.send_signal(signal.SIGINT)
                try:
                    process.wait(STOP_GRACE_S)
                except subprocess.TimeoutExpired:
                    self.console.say(f"\n{name} did not stop within {STOP_GRACE_S:.0f}s; killing it", err=True)
                    process.kill()
                    process.wait()

    def _resume_flags(self, role: Role, first: bool) -> list[str]:
        if role.name == "replay":
            return ["--resume"] if self.resume or not first else []
        if role.name == "learner" and (self.resume or not first) and self.run.checkpoint.exists():
            return ["--resume"]
        return []

    def _start(self, role: Role, first: bool = False) -> None:
        log = open(self.run.log(role.name), "ab")
        command = [sys.executable, "-m", *role.module.split(), *self.base, *role.flags,
                   *self._resume_flags(role, first)]  # module, then any subcommand
        role.process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                        start_new_session=True, env=env_stopping_with_this())
        role.started = time.monotonic()
        log.close()


def keeping(config: Config) -> str:
    """What the learner keeps for the greedy learning curve (`evaluate --curve`), for the start line."""
    learner = config.learner
    rules = ([f"every {learner.keep_every:,d} updates"] if learner.keep_every else []) + \
        ([f"every {learner.keep_every_s:g} s"] if learner.keep_every_s else [])
    if not rules:
        return "no policies kept (learner.keep_every 0)"
    return f"a policy kept {' or '.join(rules)} into {RunDir.of(config).policies.name}/"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="deploy/run.sh",
        description="Run the whole system locally: replay + learner + actors over loopback Zenoh. "
                    "Everything for the run goes to its run folder, <run.runs_dir>/<run.name>/.")
    parser.add_argument("--actors", type=int, default=None,
                        help="number of actors (default: actor.num_actors, or one per spare core)")
    parser.add_argument("--port", type=int, default=0, help="loopback port of the replay's router (default: a free one)")
    parser.add_argument("--resume", action="store_true",
                        help="continue the run: the learner from its latest checkpoint, the replay from its "
                             "snapshot and counters")
    parser.add_argument("--tensorboard", action="store_true",
                        help="the recorder also writes the run's curves as TensorBoard event files into <run "
                             "folder>/tensorboard/ while it trains (`tensorboard --logdir <run.runs_dir>`); "
                             "needs recorder.enabled")
    add_config_arguments(parser)
    return parser


def stack_precisions(config: Config) -> dict[str, str]:
    """The precision options of the processes this stack starts here: the actors', and the learner's on a CPU."""
    precisions = {"actor.inference": config.actor.inference}
    if config.learner.precision == "bfloat16":
        from common.network import resolve_device  # torch: only for the one value that may be refused
        if resolve_device(config.network).type == "cpu":
            precisions["learner.precision"] = config.learner.precision
    return precisions


def open_watcher(transport, console: Console):
    """The stack's own session to its replay's router, retried while the replay starts (each try waits
    transport.connect_timeout_s) for WATCHER_CONNECT_S; None, with a line, if it never answers or the stack
    is stopped first."""
    deadline = time.monotonic() + WATCHER_CONNECT_S
    while not console.stop.is_set():
        try:
            return open_session(transport)
        except zenoh.ZError as error:
            if time.monotonic() >= deadline:
                console.say(f"the replay's router at {transport.connect[0]} did not answer within "
                            f"{WATCHER_CONNECT_S:.0f} s ({error}); stopping the run", err=True)
                return None
            console.say(f"waiting for the replay's router at {transport.connect[0]} ...", err=True)
    return None


def main(argv: list[str] | None = None) -> int:
    args, config = parse_config_or_exit(build_parser(), argv)
    exit_if_unrunnable("deploy/run.sh", stack_precisions(config))
    if args.tensorboard and not config.recorder.enabled:
        print("deploy/run.sh: --tensorboard needs the recorder, but recorder.enabled is false", file=sys.stderr)
        return 2
    run = RunDir.of(config)
    run.root.mkdir(parents=True, exist_ok=True)
    try:
        claim = claim_run(run)  # held open until this process ends
    except RunClaimError as error:
        print(f"deploy/run.sh: {error}", file=sys.stderr)
        return 2
    remove_dead_temporaries(run.root)  # the run's other processes start after this
    try:
        write_text_atomically(run.config, to_toml(config))
    except OSError as error:  # the roles read it: a stack cannot run without it
        print(f"deploy/run.sh: cannot write {run.config}: {error}; free space and start again", file=sys.stderr)
        claim.close()
        return 1
    endpoint = f"tcp/127.0.0.1:{args.port or free_port()}"
    actors = args.actors or config.actor.num_actors or default_actor_count()
    stop = threading.Event()
    stop_with_parent(stop)  # started by the main job: a job killed leaves no stack training on alone
    console = Console(stop)
    console.say(f"run {config.run.name!r}: strategy {config.exploration.strategy}, {actors} actor(s), "
                f"router {endpoint}, files in {run.root}/; {keeping(config)}")
    stack = Stack(config, run, endpoint, actors, args.resume, args.tensorboard, console)
    on_stop_signals(lambda *_: stop.set())  # a hung-up terminal stops it as Ctrl-C does, but under nohup
    monitor = StackMonitor(config.pace.total_env_steps)
    stack.start_all()
    watcher_config = config.transport
    watcher_config.mode, watcher_config.connect, watcher_config.listen = "client", [endpoint], []
    session, subscriptions, code = None, [], 1
    keys = Keys(config.transport.namespace, config.run.name)
    try:  # from here on, whatever happens, the processes are stopped
        session = open_watcher(watcher_config, console)
        if session is None:
            return 1
        subscriptions = [subscribe(session, keys.metrics_all, monitor.on_metric),
                         subscribe(session, keys.replay_stats, monitor.on_replay_stats)]
        code = stack.watch(stop, monitor)
        if stack.processes["learner"].poll() is not None:
            monitor.learner_final.wait(FINAL_METRICS_WAIT_S)
    finally:
        console.say("\n" + monitor.line(sum(stack.restarts.values())))
        console.say("stopping processes ...")
        stack.report(monitor, "stopping")
        stack.stop_all()
        for subscription in subscriptions:
            subscription.undeclare()
        if session is not None:
            session.close()
    stack.report(monitor, "finished" if stack.learner_finished else "stopped")
    summary = monitor.summary(config, stack.restarts, stack.learner_finished)
    written = run.summary
    try:
        write_text_atomically(run.summary, json.dumps(summary, indent=2) + "\n")
    except OSError as error:  # the run itself is safe: the learner's checkpoint holds it
        console.say(f"cannot write the summary {run.summary}: {error}", err=True)
        written = "no summary written"
    ratio = summary["env_steps_per_update"]
    shown = f"{ratio:.3f}" if isinstance(ratio, (int, float)) else "unknown"
    console.say(f"run: {summary['env_steps']:,d} env steps, {summary['updates']:,d} updates, {shown} env steps "
                f"per update (configured {config.pace.env_steps_per_update:g}); {written}")
    restarted = ", ".join(f"{name} {count}" for name, count in stack.restarts.items() if count) or "none"
    console.say(f"stopped; restarts: {restarted}; logs in {run.logs}/")
    claim.close()
    return code


if __name__ == "__main__":
    run_main(main)
