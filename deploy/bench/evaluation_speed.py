"""Evaluation speed beside the batched actor's, in one run: the lockstep loop, the actor, the wall time implied.

Everything runs in this one process, pinned to one core with one torch thread,
as one evaluation worker runs when ``evaluation.workers`` equals the cores, and
as one actor of the stack runs. Both act in float32. Each round measures, in
turn (so that noise from other processes hits all alike):

* evaluation: ``run_lockstep`` exactly as a worker runs it, for each
  ``--envs`` value: that many episodes side by side, lasting to ``--cap``
  steps, as a policy that drives makes them (simulator and camera, the greedy
  network's batched forward pass, the loop's bookkeeping). An untrained
  network crashes within a few steps, so the privileged driver's actions on
  every start are recorded first (not timed) and replayed, while the greedy
  network's forward pass is paid for at every step (its actions are
  discarded); the simulator is deterministic, so the episodes are the
  driver's, to the cap;
* the batched actor: ``Actor.step`` of ``--actor-envs`` simulators acting with
  an untrained network and a started strategy, as ``actor_speed.py`` times it
  (its episodes are short: resets and frame compression at episode ends);
* the network alone: ``GreedyPolicy.act`` on random frames, for each ``--envs``.

Rates are env-steps per CPU-second of this process, i.e. per core (steadier than
wall time on a shared machine), medians of the rounds; the ratio is the
evaluation's rate over the actor's. From the evaluation's rate comes the wall
time of a full-length evaluation (episodes_per_start x 10 starts x 2 sets
episodes of max_steps steps) over ``evaluation.workers`` processes, assuming that
many free cores.

First, with ``--busy N`` (default: the cores; 0 skips it), the inference rate on 1 thread and on all
cores' threads while N spinning processes hold the cores, as a training run does beside a
curve followed with ``--follow``: the reason ``evaluation.torch_threads`` is 1 there.

    .venv/bin/python deploy/bench/evaluation_speed.py [--envs 4,16,32,64] [--actor-envs 64] [--rounds 3]
"""

from __future__ import annotations

import argparse
import itertools
import multiprocessing
import os
import statistics
import time
from typing import Iterator

import torch

from actor.evaluation.episodes import (EpisodeJob, GreedyPolicy, Policy, PrivilegedPolicy, episode_jobs,
                                       evaluation_env_config, run_lockstep)
from actor.sim import START_SETS, make_env, start_poses
from actor_speed import acting_actor, actor_speeds, inference_speed  # deploy/bench is this script's directory
from common.config import Config
from common.cpu_capability import describe_cpu
from env_speed import one_core
from learner.update import DoubleQLearner


def _spin() -> None:
    while True:
        pass


def speeds_beside_busy_cores(network, n_envs: int, seconds: float, shape: tuple[int, ...], busy: int
                            ) -> dict[int, float]:
    """Inference env-steps/s per torch thread count (1, then every core) while `busy` processes spin."""
    spinners = [multiprocessing.get_context("spawn").Process(target=_spin, daemon=True) for _ in range(busy)]
    for spinner in spinners:
        spinner.start()
    try:
        rates = {}
        for threads in sorted({1, len(os.sched_getaffinity(0))}):
            torch.set_num_threads(threads)
            rates[threads] = inference_speed(GreedyPolicy(network, n_envs), n_envs, seconds, shape)
        return rates
    finally:
        for spinner in spinners:
            spinner.terminate()
            spinner.join()


class Recording:
    """Acts as `policy` does and keeps every job's actions."""

    def __init__(self, policy: Policy) -> None:
        self.policy = policy
        self.actions: dict[EpisodeJob, list[int]] = {}
        self._slots: dict[int, list[int]] = {}

    def begin(self, slot, job, pose):
        self.policy.begin(slot, job, pose)
        self._slots[slot] = self.actions[job] = []

    def act(self, slots, observations, poses):
        chosen = self.policy.act(slots, observations, poses)
        for slot, action in zip(slots, chosen):
            self._slots[slot].append(action)
        return chosen


class PaidReplay:
    """Replays each job's recorded actions, after paying for the greedy network's forward pass."""

    def __init__(self, greedy: GreedyPolicy, recorded: dict[EpisodeJob, list[int]]) -> None:
        self.greedy, self.recorded = greedy, recorded
        self._next: dict[int, Iterator[int]] = {}

    def begin(self, slot, job, pose):
        self.greedy.begin(slot, job, pose)
        self._next[slot] = iter(self.recorded[job])

    def act(self, slots, observations, poses):
        self.greedy.act(slots, observations, poses)
        return [next(self._next[slot]) for slot in slots]


def driving_jobs(n_envs: int) -> list[EpisodeJob]:
    """One job per env, over the starts of both sets in turn (a start may come again, with its seed)."""
    return list(itertools.islice(itertools.cycle(episode_jobs(["paid"], START_SETS, 1, root_seed=0)), n_envs))


def privileged_drives(config: Config, jobs: list[EpisodeJob]) -> dict[EpisodeJob, list[int]]:
    """The privileged driver's actions on each distinct job, to the cap (or its rare crash)."""
    distinct = list(dict.fromkeys(jobs))
    recording = Recording(PrivilegedPolicy(evaluation_env_config(config), len(distinct)))
    envs = [make_env(evaluation_env_config(config)) for _ in distinct]
    run_lockstep(distinct, envs, {"paid": recording}, config.evaluation.max_steps, config.evaluation.reward_bins,
                 lambda episode: None)
    return recording.actions


def lockstep_speeds(config: Config, envs: list, policy: PaidReplay, jobs: list[EpisodeJob]
                   ) -> tuple[float, float, float]:
    """(CPU, wall) env-steps/s of one worker's lockstep loop over the jobs, one per env, and the episodes' mean
    length (the cap, unless the driver crashed)."""
    lengths: list[int] = []
    cpu, wall = time.process_time(), time.perf_counter()
    run_lockstep(jobs, envs, {"paid": policy}, config.evaluation.max_steps, config.evaluation.reward_bins,
                 lambda episode: lengths.append(episode.length))
    steps = sum(lengths)
    return steps / (time.process_time() - cpu), steps / (time.perf_counter() - wall), steps / len(lengths)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--envs", default="4,16,32,64", help="evaluation.envs_per_worker values to measure")
    parser.add_argument("--actor-envs", type=int, default=64, help="actor.envs_per_actor of the batched actor")
    parser.add_argument("--rounds", type=int, default=3, help="rounds; every measurement once per round")
    parser.add_argument("--seconds", type=float, default=4.0, help="time per actor and network measurement")
    parser.add_argument("--cap", type=int, default=200, help="steps per evaluation episode (the rate hardly depends "
                                                             "on it: one reset per cap steps)")
    parser.add_argument("--busy", type=int, default=len(os.sched_getaffinity(0)),
                        help="spinning processes beside the threads' measurement (default: the cores; 0 skips it)")
    args = parser.parse_args()
    print(f"CPU: {describe_cpu()}", flush=True)
    paper = Config().evaluation  # the protocol being estimated
    config = Config()
    config.evaluation.max_steps = args.cap
    network = DoubleQLearner(config.network, config.learner).online.eval()
    shape = network.frame_shape
    if args.busy:
        n_envs = config.evaluation.envs_per_worker
        rates = speeds_beside_busy_cores(network, n_envs, args.seconds, shape, args.busy)
        print(f"beside {args.busy} spinning process(es), {n_envs} envs, inference env-steps/s: "
              + ", ".join(f"{threads} torch thread(s) {rate:,.0f}" for threads, rate in rates.items()), flush=True)
    cpu = one_core()
    print(f"pinned to CPU {cpu}, {torch.get_num_threads()} torch thread, torch {torch.__version__}; paper's network, "
          f"float32; evaluation episodes of {args.cap} steps, the actor's as its untrained network drives", flush=True)
    sizes = [int(part) for part in args.envs.split(",")]
    jobs = {n_envs: driving_jobs(n_envs) for n_envs in sizes}
    recorded = privileged_drives(config, driving_jobs(max(sizes)))
    envs = {n_envs: [make_env(evaluation_env_config(config)) for _ in range(n_envs)] for n_envs in sizes}
    replays = {n_envs: PaidReplay(GreedyPolicy(network, n_envs), recorded) for n_envs in sizes}
    actor = acting_actor(config, args.actor_envs, "float32")
    evaluation = {n_envs: [] for n_envs in sizes}
    alone = {n_envs: [] for n_envs in sizes}
    acting: list[float] = []
    for round_number in range(args.rounds):
        for n_envs in sizes:
            evaluation[n_envs].append(lockstep_speeds(config, envs[n_envs], replays[n_envs], jobs[n_envs]))
            alone[n_envs].append(inference_speed(replays[n_envs].greedy, n_envs, args.seconds, shape,
                                                clock=time.process_time))
        acting.append(actor_speeds(actor, args.seconds)[1])
        print(f"round {round_number + 1}/{args.rounds} done", flush=True)
    report(paper, evaluation, alone, statistics.median(acting), args)


def report(paper, evaluation: dict[int, list[tuple[float, float, float]]], alone: dict[int, list[float]], actor: float,
           args: argparse.Namespace) -> None:
    episodes = paper.episodes_per_start * sum(len(start_poses(name)) for name in START_SETS)
    full_steps = episodes * paper.max_steps
    print(f"\nmedians of {args.rounds} rounds; env-steps per CPU-second (per core) unless said; batched actor, "
          f"float32, {args.actor_envs} envs: {actor:,.0f} per CPU-s")
    print(f"{'envs/worker':>11} {'evaluation per CPU-s':>21} {'(wall)':>8} {'/ actor':>8} {'network alone':>14} "
          f"{'episode length':>15} {f'full evaluation, {paper.workers} workers':>29}")
    for n_envs, rows in evaluation.items():
        per_cpu, wall, length = (statistics.median(column) for column in zip(*rows))
        full_min = full_steps / per_cpu / paper.workers / 60
        print(f"{n_envs:>11} {per_cpu:>21,.0f} {wall:>8,.0f} {per_cpu / actor:>8.2f} "
              f"{statistics.median(alone[n_envs]):>14,.0f} {length:>15,.0f} {full_min:>25.1f} min")
    print(f"full evaluation: {episodes} greedy episodes x {paper.max_steps} steps = {full_steps:,} env-steps, "
          f"{paper.workers} workers on as many free cores")


if __name__ == "__main__":
    main()
