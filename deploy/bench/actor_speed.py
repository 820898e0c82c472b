"""Actor env steps per second by actor.envs_per_actor and actor.inference, on one core with the paper's network.

One process pinned to one core with one torch thread, as one actor of the
stack runs. For each envs_per_actor and inference precision (float32, and
bfloat16 for the convolutions and the LSTM input projection: actor/batched_q.py),
taking turns within each round so that noise from other processes hits all alike:

* actor: ``Actor.step`` exactly as the actor's loop runs it (simulators,
  cameras, one batched forward pass, the exploration strategy's draws, episode
  ends with their frame compression, resets), acting with the network and a
  started strategy from the first step; an untrained network crashes within a
  few dozen steps, so resets are frequent, as in early training. Sending
  episodes (the outbox thread) is not included;
* network alone: the same batched forward pass (actor/batched_q.py) on random
  frames, by CPU time (inference_speed, which evaluation_speed.py shares).

The actor's rates are env steps per second of wall time and per second of
this process's CPU time (steadier on a shared machine: "per actor core"). Then the network's
FLOPs per env step (deploy/bench/flops.py), the one-core peak of a square GEMM in
each precision, measured in the same run, and the ceiling they set: the steps/s
an actor would reach if its network ran at that peak, with the rest of a step
as measured.
Medians over the rounds.

    .venv/bin/python deploy/bench/actor_speed.py [--envs 1,4,8,16] [--inference float32,bfloat16] [--rounds 3]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import numpy as np
import torch

from actor.evaluation.episodes import GreedyPolicy
from actor.acting import Actor
from common.cpu_capability import bfloat16_problem, describe_cpu
from common.config import Config
from common.exploration.build import make_strategy
from common.network import weights_to_numpy
from common.wire.exploration_state import exploration_message
from common.wire.messages import Weights
from env_speed import one_core  # deploy/bench is this script's directory
from deploy.bench.flops import forward_flops
from deploy.bench.gemm_peak import Clock, Gemms

SQUARE_GEMM = 2048
PEAK_TRIES = 5


def inference_speed(policy: GreedyPolicy, n_envs: int, seconds: float, shape: tuple[int, ...],
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


def acting_actor(config: Config, envs: int, inference: str = "float32") -> Actor:
    """An actor of envs simulators that acts with (untrained) weights and a started strategy."""
    actor_config = dataclasses.replace(config.actor, envs_per_actor=envs, inference=inference)
    actor = Actor(dataclasses.replace(config, actor=actor_config), 0)
    strategy = make_strategy(config.exploration, config.network.n_actions)
    strategy.start()
    actor.mailbox.offer_weights(Weights(version=0, tensors=weights_to_numpy(actor.network)))
    actor.mailbox.offer_exploration(exploration_message(strategy))
    actor.step()  # takes the mail; warms up
    assert actor.uses_network()
    return actor


def actor_speeds(actor: Actor, seconds: float) -> tuple[float, float]:
    """(wall, CPU) env steps/s of the actor's lockstep loop: every simulator acts at every step."""
    calls, wall, cpu = 0, time.perf_counter(), time.process_time()
    while time.perf_counter() - wall < seconds:
        actor.step()
        calls += 1
    steps = calls * len(actor.slots)
    return steps / (time.perf_counter() - wall), steps / (time.process_time() - cpu)


def peak_gflops(gemms: Gemms) -> float:
    """The best of a few square GEMMs on this one thread, by CPU time."""
    seconds = min(gemms.square_seconds(Clock("cpu", torch.device("cpu"))) for _ in range(PEAK_TRIES))
    return 2.0 * gemms.square ** 3 / seconds / 1e9


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--envs", default="1,4,8,16", help="envs_per_actor values to measure")
    parser.add_argument("--inference", default="float32,bfloat16", help="actor.inference values to measure")
    parser.add_argument("--rounds", type=int, default=3, help="rounds; every measurement once per round")
    parser.add_argument("--seconds", type=float, default=4.0, help="time per measurement")
    args = parser.parse_args()
    print(f"CPU: {describe_cpu()}", flush=True)
    cpu = one_core()
    config = Config()
    print(f"pinned to CPU {cpu}, {torch.get_num_threads()} torch thread, torch {torch.__version__}; paper's "
          f"network ({config.network.frame_height}x{config.network.frame_width}x{config.network.frame_channels}, "
          f"LSTM {config.network.lstm_units}), strategy {config.exploration.strategy}, env.max_steps "
          f"{config.env.max_steps}", flush=True)
    inferences = args.inference.split(",")
    if "bfloat16" in inferences and bfloat16_problem() is not None:
        inferences.remove("bfloat16")
        print(f"skipping bfloat16: {bfloat16_problem()}", flush=True)
    cases = [(int(envs), inference) for envs in args.envs.split(",") for inference in inferences]
    actors = {case: acting_actor(config, *case) for case in cases}
    networks = {case: GreedyPolicy(actor.network, case[0], actor.batched_q.precision)
                for case, actor in actors.items()}
    measured: dict[tuple[int, str], list[tuple[float, float, float]]] = {case: [] for case in cases}
    precisions = sorted({inference for _, inference in cases})
    gemms = {precision: Gemms(config, torch.device("cpu"), SQUARE_GEMM, getattr(torch, precision))
             for precision in precisions}
    peaks: dict[str, list[float]] = {precision: [] for precision in precisions}
    for round_number in range(args.rounds):
        for precision in precisions:
            peaks[precision].append(peak_gflops(gemms[precision]))
        for case, actor in actors.items():
            network = inference_speed(networks[case], case[0], args.seconds, actor.network.frame_shape,
                                     clock=time.process_time)
            measured[case].append((*actor_speeds(actor, args.seconds), network))
        print(f"round {round_number + 1}/{args.rounds} done", flush=True)

    peak = {precision: statistics.median(found) for precision, found in peaks.items()}
    flop_per_step = sum(forward_flops(config.network, traces=1, steps=1).values())
    print(f"\nnetwork: {flop_per_step / 1e6:.1f} MFLOP per env step (deploy/bench/flops.py); one-core peak, square GEMM "
          f"{SQUARE_GEMM}: " + ", ".join(f"{name} {value:.1f} GFLOP/s" for name, value in peak.items())
          + f" (medians of rounds); medians of {args.rounds} rounds of {args.seconds:g} s")
    print(f"{'envs/actor':>10} {'inference':>9} {'actor steps/s':>14} {'per CPU-s':>10} "
          f"{'network alone, per CPU-s':>25} {'net % peak':>11} {'rest ms/step':>13} {'ceiling steps/s':>16}")
    for (envs, inference), rows in measured.items():
        wall, cpu_speed, network = (statistics.median(column) for column in zip(*rows))
        rest_s = 1.0 / cpu_speed - 1.0 / network
        ceiling = 1.0 / (flop_per_step / (peak[inference] * 1e9) + rest_s)
        share = flop_per_step * network / (peak[inference] * 1e9)
        print(f"{envs:>10} {inference:>9} {wall:>14,.0f} {cpu_speed:>10,.0f} {network:>25,.0f} "
              f"{100 * share:>10.0f}% {1e3 * rest_s:>13.3f} {ceiling:>16,.0f}")
    print("rest: everything of a step but the forward pass (simulator, camera, exploration, episode ends); "
          "ceiling: the actor's steps/s with its network at the measured peak of its precision")


if __name__ == "__main__":
    main()
