"""Learner updates per second, one-pass against the paper's separate passes, and actor inference rate.

Same random batch and same initial weights for every variant; the variants take
turns within each repetition so that machine noise hits them alike. Warm-up
updates are excluded. Sizes come from the config (paper: B = 10, T = 10,
RGB 66 x 200, LSTM 512); torch keeps its default thread count, printed.

    .venv/bin/python deploy/bench/learner_speed.py [--repeats 5] [--updates 5] [--actor-steps 300]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from common.config import Config, add_config_arguments, parse_config_or_exit
from common.network import D3RQN, resolve_device
from learner.reference_update import paper_reference_loss, same_history_reference_loss
from learner.update import DoubleQLearner, TraceBatch, one_pass_loss, to_tensors

VARIANTS = {  # name: (loss function, with_q_after)
    "paper reference (3 separate passes)": (paper_reference_loss, False),
    "same-history reference (3 passes)": (same_history_reference_loss, False),
    "one-pass": (one_pass_loss, False),
    "one-pass + VDBE after-pass": (one_pass_loss, True),
}


def random_batch(config: Config, seed: int = 0) -> TraceBatch:
    rng = np.random.default_rng(seed)
    net, learner = config.network, config.learner
    steps = (learner.batch_size, learner.trace_length)
    frames = (learner.batch_size, learner.trace_length + 1, net.frame_height, net.frame_width, net.frame_channels)
    return TraceBatch(observations=rng.integers(0, 256, frames, dtype=np.uint8),
                      actions=rng.integers(0, net.n_actions, steps), rewards=rng.random(steps).astype(np.float32),
                      terminated=np.zeros(steps, bool))


def updates_per_second(learner: DoubleQLearner, batch: TraceBatch, updates: int, with_q_after: bool) -> float:
    started = time.perf_counter()
    for _ in range(updates):
        learner.update(batch, with_q_after=with_q_after)
    return updates / (time.perf_counter() - started)


def bench_learner(config: Config, repeats: int, updates: int, warmup: int) -> dict[str, list[float]]:
    batch = random_batch(config)
    learners = {name: DoubleQLearner(config.network, config.learner, loss) for name, (loss, _) in VARIANTS.items()}
    for name, learner in learners.items():
        updates_per_second(learner, batch, warmup, VARIANTS[name][1])
    rates: dict[str, list[float]] = {name: [] for name in VARIANTS}
    for repeat in range(repeats):
        for name, learner in learners.items():
            rates[name].append(updates_per_second(learner, batch, updates, VARIANTS[name][1]))
        progress = ", ".join(f"{name.split(' (')[0]} {values[-1]:.2f}/s" for name, values in rates.items())
        print(f"  repeat {repeat + 1}/{repeats}: {progress}", flush=True)
    return rates


def paper_history_gap(config: Config) -> tuple[float, float]:
    """Relative loss difference and max |Q(h_t+1)| difference, one-pass vs paper passes, same weights and batch."""
    learner = DoubleQLearner(config.network, config.learner)
    tensors = to_tensors(random_batch(config), config.network, config.learner.trace_length, learner.device)
    gamma, n_mask = config.learner.gamma, config.learner.n_mask
    with torch.no_grad():
        one = one_pass_loss(learner.online, learner.target, tensors, gamma, n_mask)
        paper = paper_reference_loss(learner.online, learner.target, tensors, gamma, n_mask)
    relative = abs(one.loss.item() - paper.loss.item()) / one.loss.item()
    return relative, (one.next_q_values - paper.next_q_values).abs().max().item()


def bench_actor_steps(config: Config, steps: int, repeats: int) -> list[float]:
    """Single-frame forward passes per second, batch 1, carrying the LSTM state."""
    device = resolve_device(config.network)
    network = D3RQN(config.network).to(device).eval()
    net = config.network
    frames = torch.randint(0, 256, (steps, 1, 1, net.frame_height, net.frame_width, net.frame_channels),
                           dtype=torch.uint8, device=device)
    rates = []
    with torch.inference_mode():
        for repeat in range(repeats + 1):  # the first round warms up
            state = network.initial_state(1)
            started = time.perf_counter()
            for frame in frames:
                q_values, state = network(frame, state)
                q_values.cpu()
            if repeat:
                rates.append(steps / (time.perf_counter() - started))
    return rates


def describe(values: list[float]) -> str:
    return f"median {statistics.median(values):7.2f}  best {max(values):7.2f}  worst {min(values):7.2f}"


def ratio(faster: list[float], slower: list[float]) -> str:
    """Speed-up by medians and by best rounds (the least disturbed on a shared machine)."""
    return (f"{statistics.median(faster) / statistics.median(slower):.3f} by medians, "
            f"{max(faster) / max(slower):.3f} by best rounds")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="learner_speed", description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="timed rounds per variant (default 5)")
    parser.add_argument("--updates", type=int, default=5, help="updates per round (default 5)")
    parser.add_argument("--warmup", type=int, default=2, help="untimed updates per variant first (default 2)")
    parser.add_argument("--actor-steps", type=int, default=300, help="single steps per actor round (default 300)")
    add_config_arguments(parser)
    args, config = parse_config_or_exit(parser, argv)
    net, learner = config.network, config.learner

    print(f"torch {torch.__version__}, device {resolve_device(net)}, torch.get_num_threads() = {torch.get_num_threads()}")
    print(f"batch B={learner.batch_size} T={learner.trace_length} frames {net.frame_height}x{net.frame_width}"
          f"x{net.frame_channels}, LSTM {net.lstm_units}, {args.repeats} rounds x {args.updates} updates "
          f"after {args.warmup} warm-up updates", flush=True)
    rates = bench_learner(config, args.repeats, args.updates, args.warmup)

    print("\nlearner updates per second")
    for name, values in rates.items():
        print(f"  {name:38s} {describe(values)}")
    one, vdbe = rates["one-pass"], rates["one-pass + VDBE after-pass"]
    print(f"  one-pass / paper reference:        {ratio(one, rates['paper reference (3 separate passes)'])}")
    print(f"  one-pass / same-history reference: {ratio(one, rates['same-history reference (3 passes)'])}")
    extra_ms = 1e3 / statistics.median(vdbe) - 1e3 / statistics.median(one)
    print(f"  VDBE after-pass: +{extra_ms:.1f} ms per update by medians "
          f"(+{100 * (statistics.median(one) / statistics.median(vdbe) - 1):.0f}%), "
          f"+{1e3 / max(vdbe) - 1e3 / max(one):.1f} ms by best rounds")

    relative, q_gap = paper_history_gap(config)
    print(f"\none-pass vs paper passes on the same weights and batch: relative loss difference {relative:.2e}, "
          f"max |Q(h_t+1) difference| {q_gap:.2e} (h_t+1 has one frame more history in one-pass)")

    print(f"\nactor single-step inference (batch 1, one frame, state carried, inference_mode)", flush=True)
    steps = bench_actor_steps(config, args.actor_steps, args.repeats)
    print(f"  steps per second {describe(steps)}")


if __name__ == "__main__":
    main()
