"""Chaos run: a local stack trains while a process of it (replay, learner, recorder or an actor) is SIGKILLed
every few minutes; then the run is closed at a budget just ahead of it, and checked.

    .venv/bin/python deploy/labs/chaos.py --minutes 30                          # the paper's local job, 1-3 min apart
    .venv/bin/python deploy/labs/chaos.py --minutes 1 --kill-every 8 12 --cycle --preset smoke ...   # the CI test's

What it checks, into <run>/chaos/report.json and report.md (exit code 0 when all hold):

- alive: after the last kill every process of the stack runs again (the stack restarted it);
- snapshot: every killed replay came back with at least the episodes its snapshot's manifest named just
  before the kill, none of them skipped as damaged;
- ratio: once the run is closed (the stack resumed with a budget just past its env steps, so that it ends
  by itself), the learner's updates pay for every env step the replay took, at most
  pace.error_buffer_updates more;
- log: every flight-log segment of the run reads to its end (a killed recorder's up to its last flush).

It samples the processes' memory and the run folder's size as deploy/labs/soak.py does, into <run>/soak/.
Flags it does not know go to deploy/run.sh (deploy/launcher/stack.py), e.g. --preset, --run.name, --actors.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from common.atomic_file import pid_alive
from common.checkpoint import Checkpoint
from common.config_cli import config_from_args, parse_flags
from common.config_values import load_config
from common.pacing import achieved_ratio, updates_paid_for
from common.run_dir import RunDir, RunStatus, StatusError
from deploy.labs import soak
from deploy.launcher.stack import build_parser
from replay.recorder.reader import LogError, LogFile
from replay.snapshot import manifest_held

ROOT = Path(__file__).resolve().parents[2]
STACK = ROOT / "deploy" / "launcher" / "stack.py"
RESTORED = re.compile(r"restored (\d+) episodes from the snapshot .*\((\d+) records skipped\)")


@dataclass
class Kill:
    at_s: float  # since the chaos began
    process: str
    pid: int
    promised: int | None = None  # a replay: the episodes its snapshot's manifest named just before the kill
    restored: int | None = None  # ... and the episodes the new replay restored
    skipped: int | None = None
    replaced_after_s: float | None = None  # until the stack ran a new process in its place


@dataclass
class Chaos:
    run: RunDir
    stack_flags: list[str]
    kills: list[Kill] = field(default_factory=list)
    checks: dict[str, bool] = field(default_factory=dict)
    facts: dict = field(default_factory=dict)


def start_stack(flags: list[str], out: Path) -> subprocess.Popen:
    out.parent.mkdir(parents=True, exist_ok=True)
    return subprocess.Popen([sys.executable, str(STACK), *flags], cwd=ROOT, stdout=out.open("ab"),
                            stderr=subprocess.STDOUT, start_new_session=True)


def status(run: RunDir) -> RunStatus | None:
    try:
        return RunStatus.read(run.status)
    except StatusError:
        return None


def wait_until(condition, timeout_s: float, poll_s: float = 0.5) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(poll_s)
    return False


def restored_lines(run: RunDir) -> list[tuple[int, int]]:
    """(episodes, records skipped) of every snapshot restore the replay's log tells of, in order."""
    try:
        text = run.log("replay").read_text(errors="replace")
    except OSError:
        return []
    return [(int(episodes), int(skipped)) for episodes, skipped in RESTORED.findall(text)]


def kill_one(chaos: Chaos, process: str, started: float, settle_s: float) -> Kill:
    run = chaos.run
    before = status(run)
    pid = before.pids[process]
    kill = Kill(round(time.monotonic() - started, 1), process, pid)
    restores = len(restored_lines(run))
    if process == "replay":
        held = manifest_held(run.replay_snapshot)
        kill.promised = held.episodes if held else None
    os.kill(pid, signal.SIGKILL)
    killed_at = time.monotonic()
    if wait_until(lambda: (now := status(run)) is not None and now.pids.get(process, pid) != pid
                  and pid_alive(now.pids[process]), settle_s):
        kill.replaced_after_s = round(time.monotonic() - killed_at, 1)
    if process == "replay" and wait_until(lambda: len(restored_lines(run)) > restores, settle_s):
        kill.restored, kill.skipped = restored_lines(run)[restores]
    print(f"chaos: +{kill.at_s:.0f}s killed {process} (pid {pid}); "
          f"{'replaced after %.1f s' % kill.replaced_after_s if kill.replaced_after_s is not None else 'NOT replaced'}"
          + (f"; snapshot promised {kill.promised}, restored {kill.restored} ({kill.skipped} skipped)"
             if process == "replay" else ""), flush=True)
    return kill


def unleash(chaos: Chaos, seconds: float, every: tuple[float, float], cycle: bool, seed: int,
            settle_s: float, soak_every_s: float) -> None:
    """Kills a process every `every` seconds (uniform) for `seconds`, sampling the soak figures meanwhile."""
    rng, started, turn = random.Random(seed), time.monotonic(), 0
    next_kill, next_sample = started + rng.uniform(*every), started
    while (now := time.monotonic()) < started + seconds:
        current = status(chaos.run)
        if current is not None and now >= next_sample:
            soak.append(chaos.run.soak / "soak.csv", soak.sample(chaos.run, current))
            next_sample = now + soak_every_s
        if current is not None and now >= next_kill:
            processes = sorted(current.pids)
            process = processes[turn % len(processes)] if cycle else rng.choice(processes)
            turn += 1
            chaos.kills.append(kill_one(chaos, process, started, settle_s))
            next_kill = time.monotonic() + rng.uniform(*every)
        time.sleep(0.2)


def check_alive(chaos: Chaos, settle_s: float) -> bool:
    """Every process of the stack runs, and the stack has restarted nothing for a few seconds."""
    def settled() -> bool:
        first = status(chaos.run)
        time.sleep(3.0)
        last = status(chaos.run)
        return (first is not None and last is not None and first.restarts == last.restarts
                and all(pid_alive(pid) for pid in last.pids.values()))
    return wait_until(settled, settle_s, poll_s=0.0)


def close_run(chaos: Chaos, out: Path, timeout_s: float) -> int | None:
    """Resumes the stopped run with a budget just past its env steps, so that it closes and ends by itself."""
    counters = json.loads(chaos.run.replay_counters.read_text())
    budget = int(counters["env_steps"]) + 1
    chaos.facts["closing_budget"] = budget
    stack = start_stack([*chaos.stack_flags, "--resume", "--pace.total_env_steps", str(budget)], out)
    try:
        return stack.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return None
    finally:
        if stack.poll() is None:  # timed out, or this script was stopped
            stop_stack(stack)


def stop_stack(stack: subprocess.Popen, timeout_s: float = 120.0) -> int:
    stack.send_signal(signal.SIGINT)
    try:
        return stack.wait(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(stack.pid, signal.SIGKILL)
        return stack.wait()


def check_ratio(chaos: Chaos) -> bool:
    config = load_config(toml_path=chaos.run.config)
    counters = json.loads(chaos.run.replay_counters.read_text())
    due = updates_paid_for(counters["env_steps"], counters["start_mark"], config.pace.env_steps_per_update)
    updates = Checkpoint.load(chaos.run.checkpoint).updates
    buffer = config.pace.error_buffer_updates
    chaos.facts.update(updates=updates, updates_due=round(due, 2), error_buffer_updates=buffer,
                       env_steps=counters["env_steps"], lost_updates=counters.get("lost_updates", 0),
                       recounted_updates=counters.get("recounted_updates", 0),
                       env_steps_per_update=round(achieved_ratio(counters["env_steps"], counters["start_mark"], updates), 4))
    return due <= updates <= due + buffer


def check_log(chaos: Chaos) -> bool:
    segments = {}
    for path in chaos.run.wire_log_segments():
        try:
            with LogFile(path, unfinished_ok=True) as log:
                segments[path.name] = sum(1 for _ in log.records())
        except LogError as error:
            segments[path.name] = f"unreadable: {error}"
    chaos.facts["log_segments"] = segments
    return bool(segments) and all(isinstance(count, int) for count in segments.values())


def write_report(chaos: Chaos) -> None:
    folder = chaos.run.root / "chaos"
    folder.mkdir(parents=True, exist_ok=True)
    report = {"checks": chaos.checks, "facts": chaos.facts, "kills": [asdict(kill) for kill in chaos.kills]}
    (folder / "report.json").write_text(json.dumps(report, indent=2) + "\n")
    lines = [f"# Chaos run {chaos.run.root.name}", "", "| check | holds |", "|---|---|",
             *(f"| {name} | {'yes' if held else 'NO'} |" for name, held in chaos.checks.items()), "",
             "| +s | killed | replaced after s | snapshot promised | restored (skipped) |", "|---:|---|---:|---:|---:|",
             *(f"| {k.at_s:.0f} | {k.process} | {k.replaced_after_s} | {k.promised if k.promised is not None else ''} | "
               f"{'' if k.restored is None else f'{k.restored} ({k.skipped})'} |" for k in chaos.kills),
             "", "```", json.dumps(chaos.facts, indent=1), "```"]
    (folder / "report.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="deploy/labs/chaos.py", description=__doc__.splitlines()[0],
                                     usage="deploy/labs/chaos.py [options] [flags of deploy/run.sh]")
    parser.add_argument("--minutes", type=float, default=30.0, help="how long the killing goes on (default 30)")
    parser.add_argument("--kill-every", type=float, nargs=2, default=(60.0, 180.0), metavar=("MIN_S", "MAX_S"),
                        help="seconds between kills, drawn uniformly (default 60 180)")
    parser.add_argument("--cycle", action="store_true", help="kill the processes in turn instead of at random")
    parser.add_argument("--seed", type=int, default=0, help="seed of the draws (default 0)")
    parser.add_argument("--settle-s", type=float, default=120.0,
                        help="how long a killed process may take to run again (default 120)")
    parser.add_argument("--soak-every", type=float, default=30.0, help="seconds between soak samples (default 30)")
    parser.add_argument("--close-timeout-s", type=float, default=900.0,
                        help="how long the closing run may take to end by itself (default 900)")
    args, stack_flags = parser.parse_known_args(argv)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))  # SIGTERM unwinds, so the stacks started are stopped
    stack_flags = stack_flags or ["--preset", "local", "--run.name", "chaos", "--pace.total_env_steps", "100000000"]
    config = load_config_of(stack_flags)
    chaos = Chaos(RunDir.of(config), stack_flags)
    out = chaos.run.root / "chaos" / "stack.out"
    stack = start_stack(stack_flags, out)
    try:
        if not wait_until(lambda: (now := status(chaos.run)) is not None and now.updates > 0, args.settle_s * 5):
            print("chaos: the stack never started training", file=sys.stderr)
            return 1
        unleash(chaos, 60 * args.minutes, tuple(args.kill_every), args.cycle, args.seed, args.settle_s,
                args.soak_every)
        chaos.checks["alive"] = check_alive(chaos, args.settle_s)
    finally:
        chaos.facts["stack_exit_code"] = stop_stack(stack)
    chaos.checks["snapshot"] = all(kill.restored is not None and kill.skipped == 0
                                   and kill.restored >= min(kill.promised or 0, config.replay.capacity)
                                   for kill in chaos.kills if kill.process == "replay")
    chaos.facts["closing_exit_code"] = close_run(chaos, out, args.close_timeout_s)
    chaos.checks["closed"] = chaos.facts["closing_exit_code"] == 0
    chaos.checks["ratio"] = chaos.checks["closed"] and check_ratio(chaos)
    chaos.checks["log"] = check_log(chaos)
    write_report(chaos)
    if (chaos.run.soak / "soak.csv").exists():
        soak.report(chaos.run)
    return 0 if all(chaos.checks.values()) else 1


def load_config_of(stack_flags: list[str]):
    """The run's config as the stack will resolve it from the same flags."""
    return config_from_args(parse_flags(build_parser(), stack_flags))


if __name__ == "__main__":
    sys.exit(main())
