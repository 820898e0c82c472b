"""The learner's updates/s with a greedy curve followed beside it, side by side with the learner alone.

A curve followed during training (`evaluate --curve RUN --follow --nice 15`) runs evaluation workers on
the learner's cores. An update runs its torch threads in step, so one thread waiting on a core a worker
holds stalls the whole update, and the niceness does not help (issue 38, item 7). In each round, in turn
(so that noise from other processes hits all cases alike):

* alone: the learner on `--learner-threads` threads (default: every core), nothing beside;
* crowded: the same learner, beside a follower of every core's worth of workers, 1 torch thread each, at
  nice 15: what `evaluate --follow` ran before it warned (`evaluate` now warns on this layout);
* shared: the learner on one core fewer, beside a follower of 1 worker x 1 thread at nice 15: the layout
  `deploy/grid/experiments.py --curve-beside` and `evaluate`'s warning give;
* alone, one core fewer: the learner of `shared`, nothing beside (what the follower itself costs).

The learner is `DoubleQLearner.update` on one batch of the config's sizes (paper: B = 10, T = 10, LSTM
512), timed on the wall clock over `--seconds`, after the follower's workers have started. The follower is
the real `evaluate` on `--policy` (a kept policy; default: the config's untrained network, whose episodes
end in a few steps, so its workers reset simulators more than a driving policy's do). Only the learner
is timed: the stack's actor and replay would take CPU from both cases alike.

    .venv/bin/python deploy/bench/follow_beside.py [--seconds 40] [--rounds 2] [--policy runs/X/policies/P.pt]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import signal
import statistics
import subprocess
import sys
import time
from pathlib import Path
from tempfile import TemporaryDirectory

import torch

from common.checkpoint import KeptPolicy
from common.config import Config
from common.config_cli import add_config_arguments, parse_config_or_exit
from common.config_values import to_dict
from common.cpu_capability import describe_cpu
from common.eta import Eta
from deploy.bench.learner_speed import random_batch
from learner.update import DoubleQLearner

FOLLOWER_NICE = 15
WORKER_START_S = 12.0  # the follower's workers import torch and build simulators before they act


@dataclasses.dataclass(frozen=True)
class Case:
    name: str
    learner_threads: int
    follower_workers: int  # 0: nothing beside


def cases(cores: int, learner_threads: int) -> list[Case]:
    fewer = max(1, learner_threads - 1)
    return [Case("alone", learner_threads, 0), Case("crowded", learner_threads, cores),
            Case("shared", fewer, 1), Case("alone, one core fewer", fewer, 0)]


def untrained_policy(config: Config, folder: Path) -> Path:
    learner = DoubleQLearner(config.network, config.learner)
    policy = KeptPolicy(updates=0, env_steps=0, wall_s=0.0, cpu=describe_cpu(), config=to_dict(config),
                        online=learner.online.state_dict())
    return policy.save(folder / "untrained.pt")


def start_follower(policy: Path, workers: int, out: Path) -> subprocess.Popen:
    """`evaluate` on the policy with `workers` workers x 1 torch thread at nice 15, long enough to outlast a case."""
    command = [sys.executable, "-m", "actor.evaluation.command", "--checkpoint", str(policy), "--nice", str(FOLLOWER_NICE),
               "--no-random-baseline", "--out", str(out), "--evaluation.workers", str(workers),
               "--evaluation.torch_threads", "1", "--evaluation.episodes_per_start", "500"]
    return subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)


def learner_speed(learner: DoubleQLearner, batch, threads: int, seconds: float) -> float:
    torch.set_num_threads(threads)
    learner.update(batch)  # the new thread count's pools
    updates, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds:
        learner.update(batch)
        updates += 1
    return updates / (time.perf_counter() - started)


def measure_case(case: Case, learner: DoubleQLearner, batch, policy: Path, seconds: float, out: Path) -> float:
    if not case.follower_workers:
        return learner_speed(learner, batch, case.learner_threads, seconds)
    follower = start_follower(policy, case.follower_workers, out)
    try:
        time.sleep(WORKER_START_S)
        speed = learner_speed(learner, batch, case.learner_threads, seconds)
    finally:
        if follower.poll() is None:
            os.killpg(follower.pid, signal.SIGKILL)
            follower.wait()
    if follower.returncode not in (-signal.SIGKILL, 0):
        raise RuntimeError(f"the follower failed (exit {follower.returncode}): case {case.name!r} not measured")
    return speed


def markdown(header: str, speeds: dict[Case, list[float]]) -> str:
    base = statistics.median(next(iter(speeds.values())))
    lines = [header, "", "| case | learner threads | follower (nice 15) | updates/s, median (rounds) | vs alone |",
             "|---|---:|---|---:|---:|"]
    for case, values in speeds.items():
        follower = f"{case.follower_workers} worker(s) x 1 thread" if case.follower_workers else "none"
        rounds = ", ".join(f"{value:.2f}" for value in values)
        lines.append(f"| {case.name} | {case.learner_threads} | {follower} | {statistics.median(values):.2f} "
                     f"({rounds}) | {statistics.median(values) / base:.0%} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="follow_beside", description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=40.0, help="timed seconds per case per round (default 40)")
    parser.add_argument("--rounds", type=int, default=2, help="rounds; every case once per round (default 2)")
    parser.add_argument("--learner-threads", type=int, default=os.cpu_count() or 1,
                        help="the learner's torch threads when alone (default: the cores)")
    parser.add_argument("--policy", type=Path, help="the kept policy the follower evaluates (default: untrained)")
    add_config_arguments(parser)
    args, config = parse_config_or_exit(parser, argv)
    cores = os.cpu_count() or 1
    learner = DoubleQLearner(config.network, config.learner)
    batch = learner.prepare(random_batch(config))
    plan = cases(cores, args.learner_threads)
    speeds: dict[Case, list[float]] = {case: [] for case in plan}
    eta = Eta(args.rounds * len(plan))
    with TemporaryDirectory() as folder:
        policy = args.policy or untrained_policy(config, Path(folder))
        for round_ in range(args.rounds):
            for index, case in enumerate(plan):
                out = Path(folder) / f"follower-{round_}-{index}"
                speeds[case].append(measure_case(case, learner, batch, policy, args.seconds, out))
                eta.update(round_ * len(plan) + index + 1)
                print(f"  round {round_ + 1}/{args.rounds}, {case.name}: {speeds[case][-1]:.2f} updates/s, "
                      f"ETA {eta.text()}", file=sys.stderr, flush=True)
    header = (f"CPU: {describe_cpu()}, {cores} cores; torch {torch.__version__}; learner precision "
              f"{config.learner.precision}, LSTM {config.network.lstm_units}; follower policy "
              f"{args.policy or 'untrained'}; {args.rounds} rounds x {args.seconds:.0f} s per case")
    print(markdown(header, speeds), flush=True)


if __name__ == "__main__":
    main()
