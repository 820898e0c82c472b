"""What recording real LSTM states in the random phase costs an actor (learner.stored_state, issue 39).

Before the learner's first weights an actor acts uniformly at random. With learner.stored_state it still runs
its network, the learner's initial one, so that the random phase's episodes store real (h, c) rows rather than
zero rows mid-episode (docs/method.md, learner.stored_state). This times random-phase actor steps both ways: the
network skipped (zero rows, the code before) and run (real rows); rounds interleave the two, so that noise from
other processes hits both alike, and the best round of each is kept. Sizes are the preset's (paper's network).

    .venv/bin/python deploy/bench/random_phase_states.py --preset local --envs 1 --steps 300 --rounds 4
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import torch

from actor.acting import Actor
from common.config_values import load_config
from common.cpu_capability import describe_cpu


def seconds_per_step(actor: Actor, steps: int) -> float:
    """Wall seconds of one lockstep step, averaged over `steps` steps (each steps every simulator once)."""
    started = time.perf_counter()
    for _ in range(steps):
        actor.step()
    return (time.perf_counter() - started) / steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", default="local")
    parser.add_argument("--envs", type=int, default=1, help="actor.envs_per_actor")
    parser.add_argument("--steps", type=int, default=300, help="lockstep steps a round")
    parser.add_argument("--rounds", type=int, default=4, help="rounds; the first warms up and is not counted")
    args = parser.parse_args()
    torch.set_num_threads(1)  # an actor's one core (actor/runner.py)
    config = load_config(args.preset, overrides={"learner.stored_state": True, "learner.burn_in": 2})
    config = dataclasses.replace(config, actor=dataclasses.replace(config.actor, envs_per_actor=args.envs))
    real_rows = Actor(config, actor_id=0)
    zero_rows = Actor(config, actor_id=0)
    zero_rows._q_values = lambda running: None  # the random phase as it was: no network, zero rows
    best = {"zero rows": float("inf"), "real rows": float("inf")}
    for round_ in range(args.rounds):
        for name, actor in (("zero rows", zero_rows), ("real rows", real_rows)):
            seconds = seconds_per_step(actor, args.steps)
            if round_:
                best[name] = min(best[name], seconds)
    print(f"{describe_cpu()}; network {config.network.frame_height} x {config.network.frame_width}, "
          f"{config.network.lstm_units} units; 1 torch thread, {args.envs} simulator(s)")
    for name, seconds in best.items():
        print(f"random phase, {name}: {args.envs / seconds:.1f} env steps/s ({1e3 * seconds:.2f} ms a lockstep step)")
    print(f"real rows take {best['real rows'] / best['zero rows']:.2f}x the time of zero rows")


if __name__ == "__main__":
    main()
