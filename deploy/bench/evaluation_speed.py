"""Evaluation speed: batched greedy inference, the full lockstep loop, and the wall time it implies.

Everything runs in this one process, pinned to one core with one torch thread,
as one evaluation worker is when ``evaluation.workers`` equals the cores:

* inference: ``GreedyPolicy.act`` alone (stacking frames, gathering and
  scattering per-env LSTM states, one forward pass) over random frames, for
  each ``envs_per_worker``; env-steps/s = envs x passes / seconds;
* lockstep loop: ``run_lockstep`` exactly as a worker runs it, with episodes
  that last to the cap. An untrained network crashes within a few steps, so
  the bench drives with the privileged driver while still paying for the
  greedy network's batched forward pass at every step (its actions are
  discarded). Per env-step: simulator + camera + network + privileged driver.

First, with ``--busy N`` (default: the cores), the inference rate on 1 thread and on all
cores' threads while N spinning processes hold the cores, as a training run does beside a
curve followed with ``--follow``: the reason ``evaluation.torch_threads`` is 1 there.

From the lockstep rate it estimates the wall time of a full-length evaluation
(episodes_per_start x 10 starts x 2 sets episodes of max_steps steps each)
over ``evaluation.workers`` processes, assuming that many free cores. The
machine may be shared: the figures are what was measured.

    .venv/bin/python deploy/bench/evaluation_speed.py [--envs 1,4,8] [--seconds 3] [--cap 300]
"""

from __future__ import annotations

import argparse
import itertools
import multiprocessing
import os
import time

import numpy as np
import torch

from actor.evaluation.episodes import (GreedyPolicy, PrivilegedPolicy, episode_jobs, evaluation_env_config,
                                       run_lockstep)
from actor.sim import START_SETS, make_env, start_poses
from common.cpu_capability import describe_cpu
from common.config import Config
from env_speed import one_core  # deploy/bench is this script's directory
from learner.update import DoubleQLearner


def inference_rate(policy: GreedyPolicy, n_envs: int, seconds: float, shape: tuple[int, ...],
                   clock=time.perf_counter) -> float:
    """Env-steps/s of the policy's batched forward pass over random frames, by wall time or another clock."""
    slots = list(range(n_envs))
    rng = np.random.default_rng(0)
    observations = [rng.integers(0, 256, size=shape, dtype=np.uint8) for _ in slots]
    poses = [(0.0, 0.0, 0.0)] * n_envs
    policy.act(slots, observations, poses)  # warm-up
    passes, start = 0, clock()
    while clock() - start < seconds:
        policy.act(slots, observations, poses)
        passes += 1
    return n_envs * passes / (clock() - start)


def _spin() -> None:
    while True:
        pass


def rates_beside_busy_cores(network, n_envs: int, seconds: float, shape: tuple[int, ...], busy: int
                            ) -> dict[int, float]:
    """Inference env-steps/s per torch thread count (1, then every core) while `busy` processes spin."""
    spinners = [multiprocessing.get_context("spawn").Process(target=_spin, daemon=True) for _ in range(busy)]
    for spinner in spinners:
        spinner.start()
    try:
        rates = {}
        for threads in sorted({1, len(os.sched_getaffinity(0))}):
            torch.set_num_threads(threads)
            rates[threads] = inference_rate(GreedyPolicy(network, n_envs), n_envs, seconds, shape)
        return rates
    finally:
        for spinner in spinners:
            spinner.terminate()
            spinner.join()


class PaidGreedyPrivileged:
    """Acts as the privileged driver, after paying for the greedy network's forward pass."""

    def __init__(self, greedy: GreedyPolicy, privileged: PrivilegedPolicy) -> None:
        self.greedy, self.privileged = greedy, privileged

    def begin(self, slot, job, pose):
        self.greedy.begin(slot, job, pose)
        self.privileged.begin(slot, job, pose)

    def act(self, slots, observations, poses):
        self.greedy.act(slots, observations, poses)
        return self.privileged.act(slots, observations, poses)


def lockstep_rate(config: Config, network, n_envs: int) -> tuple[float, int]:
    """Env-steps/s of one worker running n_envs full-length episodes side by side."""
    envs = [make_env(evaluation_env_config(config)) for _ in range(n_envs)]
    policy = PaidGreedyPrivileged(GreedyPolicy(network, n_envs), PrivilegedPolicy(evaluation_env_config(config), n_envs))
    jobs = list(itertools.islice(itertools.cycle(episode_jobs(["paid"], START_SETS, 1, root_seed=0)), n_envs))
    lengths: list[int] = []
    start = time.perf_counter()
    run_lockstep(jobs, envs, {"paid": policy}, config.evaluation.max_steps, config.evaluation.reward_bins,
                 lambda episode: lengths.append(episode.length))
    return sum(lengths) / (time.perf_counter() - start), sum(lengths)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--envs", default="1,4,8", help="envs_per_worker values to measure")
    parser.add_argument("--seconds", type=float, default=3.0, help="time per inference measurement")
    parser.add_argument("--cap", type=int, default=300, help="steps per lockstep episode (the rate does not depend on it)")
    parser.add_argument("--busy", type=int, default=len(os.sched_getaffinity(0)),
                        help="spinning processes beside the threads' measurement (default: the cores; 0 skips it)")
    args = parser.parse_args()
    print(f"CPU: {describe_cpu()}", flush=True)
    paper = Config().evaluation  # the protocol being estimated
    config = Config()
    config.evaluation.max_steps = args.cap
    network = DoubleQLearner(config.network, config.learner).online.eval()
    shape = (config.network.frame_height, config.network.frame_width, config.network.frame_channels)
    if args.busy:
        n_envs = config.evaluation.envs_per_worker
        rates = rates_beside_busy_cores(network, n_envs, args.seconds, shape, args.busy)
        print(f"beside {args.busy} spinning process(es), {n_envs} envs, inference env-steps/s: "
              + ", ".join(f"{threads} torch thread(s) {rate:,.0f}" for threads, rate in rates.items()), flush=True)
    cpu = one_core()
    print(f"pinned to CPU {cpu}, {torch.get_num_threads()} torch thread, torch {torch.__version__}")
    episodes = paper.episodes_per_start * sum(len(start_poses(name)) for name in START_SETS)
    full_steps = episodes * paper.max_steps
    print(f"{'envs/worker':>11} {'inference env-steps/s':>22} {'lockstep env-steps/s':>21} "
          f"{'(steps timed)':>14} {'full evaluation, 1 worker':>26} {f'{paper.workers} workers':>12}")
    for n_envs in (int(part) for part in args.envs.split(",")):
        inference = inference_rate(GreedyPolicy(network, n_envs), n_envs, args.seconds, shape)
        loop, timed_steps = lockstep_rate(config, network, n_envs)
        one_worker_s = full_steps / loop
        print(f"{n_envs:>11} {inference:>22,.0f} {loop:>21,.0f} {timed_steps:>14,} {one_worker_s / 60:>22.1f} min "
              f"{one_worker_s / paper.workers / 60:>8.1f} min")
    print(f"full evaluation: {episodes} greedy episodes x {paper.max_steps} steps = {full_steps:,} env-steps; "
          f"the {paper.workers}-worker column assumes {paper.workers} free cores")


if __name__ == "__main__":
    main()
