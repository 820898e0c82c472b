"""Actor env steps per second by actor.envs_per_actor, on one core with the paper's network.

One process pinned to one core with one torch thread, as one actor of the
stack runs. For each envs_per_actor, taking turns within each round so that
noise from other processes hits all alike:

* actor: ``Actor.step`` exactly as the actor's loop runs it (simulators,
  cameras, one batched forward pass, the exploration strategy's draws, episode
  ends with their frame compression, resets), acting with the network and a
  started strategy from the first step; an untrained network crashes within a
  few dozen steps, so resets are frequent, as in early training. Sending
  episodes (the outbox thread) is not included;
* network alone: the same batched forward pass (actor/batched_q.py) on random
  frames, as evaluation_speed.py times it, by CPU time.

The actor's rates are env steps per second of wall time and per second of
this process's CPU time (steadier on a shared machine: "per actor core"). Then the network's
FLOPs per env step (learner/flops.py), the one-core fp32 peak of a square GEMM
measured in the same run, and the ceiling they set: the steps/s an actor would
reach if its network ran at that peak, with the rest of a step as measured.
Medians over the rounds.

    .venv/bin/python deploy/bench/actor_speed.py [--envs 1,4,8,16] [--rounds 3] [--seconds 4]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import torch

from actor.evaluation.episodes import GreedyPolicy
from actor.runner import Actor
from common.config import Config
from common.exploration import exploration_message, make_strategy
from common.network import weights_to_numpy
from common.wire import Weights
from env_speed import one_core  # deploy/bench is this script's directory
from evaluation_speed import inference_rate
from learner.flops import forward_flops
from learner_speed import Clock, Gemms

SQUARE_GEMM = 2048
PEAK_TRIES = 5


def acting_actor(config: Config, envs: int) -> Actor:
    """An actor of envs simulators that acts with (untrained) weights and a started strategy."""
    actor = Actor(dataclasses.replace(config, actor=dataclasses.replace(config.actor, envs_per_actor=envs)), 0)
    strategy = make_strategy(config.exploration, config.network.n_actions)
    strategy.start()
    actor.mailbox.offer_weights(Weights(version=0, tensors=weights_to_numpy(actor.network)))
    actor.mailbox.offer_exploration(exploration_message(strategy))
    actor.step()  # takes the mail; warms up
    assert actor.uses_network()
    return actor


def actor_rates(actor: Actor, seconds: float) -> tuple[float, float]:
    """(wall, CPU) env steps/s of the actor's lockstep loop: every simulator acts at every step."""
    calls, wall, cpu = 0, time.perf_counter(), time.process_time()
    while time.perf_counter() - wall < seconds:
        actor.step()
        calls += 1
    steps = calls * len(actor.slots)
    return steps / (time.perf_counter() - wall), steps / (time.process_time() - cpu)


def peak_gflops(gemms: Gemms) -> float:
    """The best of a few square fp32 GEMMs on this one thread, by CPU time."""
    seconds = min(gemms.square_seconds(Clock("cpu", torch.device("cpu"))) for _ in range(PEAK_TRIES))
    return 2.0 * gemms.square ** 3 / seconds / 1e9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--envs", default="1,4,8,16", help="envs_per_actor values to measure")
    parser.add_argument("--rounds", type=int, default=3, help="rounds; every measurement once per round")
    parser.add_argument("--seconds", type=float, default=4.0, help="time per measurement")
    args = parser.parse_args()
    cpu = one_core()
    config = Config()
    print(f"pinned to CPU {cpu}, {torch.get_num_threads()} torch thread, torch {torch.__version__}; paper's "
          f"network ({config.network.frame_height}x{config.network.frame_width}x{config.network.frame_channels}, "
          f"LSTM {config.network.lstm_units}), strategy {config.exploration.strategy}, env.max_steps "
          f"{config.env.max_steps}", flush=True)
    sizes = [int(part) for part in args.envs.split(",")]
    actors = {envs: acting_actor(config, envs) for envs in sizes}
    networks = {envs: GreedyPolicy(actor.network, envs) for envs, actor in actors.items()}
    measured: dict[int, list[tuple[float, float, float]]] = {envs: [] for envs in sizes}
    gemms, peaks = Gemms(config, torch.device("cpu"), SQUARE_GEMM), []
    for round_number in range(args.rounds):
        peaks.append(peak_gflops(gemms))
        for envs, actor in actors.items():
            network = inference_rate(networks[envs], envs, args.seconds, actor.network.frame_shape,
                                     clock=time.process_time)
            measured[envs].append((*actor_rates(actor, args.seconds), network))
        print(f"round {round_number + 1}/{args.rounds} done", flush=True)

    peak = statistics.median(peaks)
    flop_per_step = sum(forward_flops(config.network, traces=1, steps=1).values())
    print(f"\nnetwork: {flop_per_step / 1e6:.1f} MFLOP per env step (learner/flops.py); one-core fp32 peak, square "
          f"GEMM {SQUARE_GEMM}: {peak:.1f} GFLOP/s (median of rounds); medians of {args.rounds} rounds of "
          f"{args.seconds:g} s")
    print(f"{'envs/actor':>10} {'actor steps/s':>14} {'per CPU-s':>10} {'network alone, per CPU-s':>25} "
          f"{'net % peak':>11} {'rest ms/step':>13} {'ceiling steps/s':>16}")
    for envs in sizes:
        wall, cpu_rate, network = (statistics.median(column) for column in zip(*measured[envs]))
        rest_s = 1.0 / cpu_rate - 1.0 / network
        ceiling = 1.0 / (flop_per_step / (peak * 1e9) + rest_s)
        print(f"{envs:>10} {wall:>14,.0f} {cpu_rate:>10,.0f} {network:>25,.0f} "
              f"{100 * flop_per_step * network / (peak * 1e9):>10.0f}% {1e3 * rest_s:>13.3f} {ceiling:>16,.0f}")
    print("rest: everything of a step but the forward pass (simulator, camera, exploration, episode ends); "
          "ceiling: the actor's steps/s with its network at the measured peak")


if __name__ == "__main__":
    main()
