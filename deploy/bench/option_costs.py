"""The cost of each learner option beyond the paper, side by side in one run on one machine.

For the paper's learner and each configuration of the study (deploy/studies/study.py CONFIGURATIONS): the bytes one
stored step takes in the replay (its frame as JPEG, measured on the simulator's own frames, plus actions,
rewards, versions and any LSTM state row), the GFLOP of one update (deploy/bench/flops.py), updates per second
(every configuration takes its turn in each round, so that noise from other processes hits all alike;
median and best round), and what the learner spends per 1,000 env steps at the configuration's update
ratio. Sizes are the paper's (B = 10, T = 10, RGB 66 x 200, LSTM 512) unless flags say otherwise.

    .venv/bin/python deploy/bench/option_costs.py --threads 1 --rounds 7 --out results/option-costs
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from actor.sim import make_env
from common.config import Config
from common.config_cli import add_config_arguments, parse_config_or_exit
from common.config_values import load_config
from common.cpu_capability import PrecisionUnavailable, describe_cpu
from common.eta import Eta
from common.wire.state_rows import STATE_DTYPE, stored_units
from common.wire.frames import FrameStack
from deploy.bench.learner_speed import random_batch
from deploy.studies.study import CONFIGURATIONS
from deploy.bench.flops import update_flops
from learner.trace_batch import TraceArrays
from learner.update import DoubleQLearner
from replay.store import step_bytes



def frame_bytes(config: Config, steps: int, seed: int = 0) -> float:
    """Mean JPEG bytes of a frame of the simulator's own episodes under random actions."""
    env = make_env(config.env, seed=seed)
    rng = np.random.default_rng(seed)
    frames = [env.reset(options={"start_set": "train"})[0]]
    while len(frames) < steps:
        observation, _, terminated, truncated, _ = env.step(int(rng.integers(config.network.n_actions)))
        frames.append(observation)
        if terminated or truncated:
            frames.append(env.reset(options={"start_set": "train"})[0])
    env.close()
    return FrameStack.from_array(np.stack(frames)).nbytes / len(frames)


def batch_for(config: Config, seed: int = 0) -> TraceArrays:
    batch = random_batch(config, seed)
    units = stored_units(config)
    if not units:
        return batch
    rows = np.random.default_rng(seed).uniform(-1, 1, (config.learner.batch_size, 2, units)).astype(STATE_DTYPE)
    return dataclasses.replace(batch, initial_state=rows)


def measure(configs: dict[str, Config], rounds: int, updates: int, warmup: int) -> dict[str, list[float]]:
    """Seconds per update of each configuration, one figure per round."""
    learners = {}
    for name, config in list(configs.items()):
        try:
            learners[name] = DoubleQLearner(config.network, config.learner)
        except PrecisionUnavailable as error:  # bfloat16 on a CPU that cannot run it
            print(f"skipping {name}: {error}", file=sys.stderr, flush=True)
            del configs[name]
    batches = {name: learners[name].prepare(batch_for(config)) for name, config in configs.items()}
    for name, learner in learners.items():
        for _ in range(warmup):
            learner.update(batches[name])
    seconds = {name: [] for name in configs}
    eta = Eta(rounds)
    eta.update(0)
    for round_ in range(rounds):
        for name, learner in learners.items():
            started = time.perf_counter()
            for _ in range(updates):
                learner.update(batches[name])
            seconds[name].append((time.perf_counter() - started) / updates)
        eta.update(round_ + 1)
        print(f"  round {round_ + 1}/{rounds}, ETA {eta.text()}", file=sys.stderr, flush=True)
    return seconds


def table(configs: dict[str, Config], seconds: dict[str, list[float]], frame: float) -> list[dict]:
    rows = []
    for name, config in configs.items():
        learner = config.learner
        per_update = statistics.median(seconds[name])
        rows.append({
            "configuration": name,
            "description": CONFIGURATIONS[name][0],
            "bytes_per_stored_step": round(frame + step_bytes(stored_units(config))),
            "gflop_per_update": sum(update_flops(config.network, learner).values()) / 1e9,
            "updates_per_s": 1.0 / per_update,
            "updates_per_s_best": 1.0 / min(seconds[name]),
            "learner_s_per_1000_env_steps": 1000.0 / config.pace.env_steps_per_update * per_update,
        })
    return rows


def markdown(rows: list[dict], header: str) -> str:
    lines = [header, "", "| Configuration | Bytes per stored step | GFLOP per update | Updates/s, median (best) | "
             "Learner s per 1,000 env steps |", "|---|---:|---:|---:|---:|"]
    for row in rows:
        lines.append(f"| {row['configuration']}: {row['description']} | {row['bytes_per_stored_step']:,d} | {row['gflop_per_update']:.2f} | "
                     f"{row['updates_per_s']:.2f} ({row['updates_per_s_best']:.2f}) | "
                     f"{row['learner_s_per_1000_env_steps']:.0f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="option_costs", description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1, help="torch threads for every update (default 1, as the "
                                                                "runs of results/time-to-drive use)")
    parser.add_argument("--rounds", type=int, default=7, help="rounds; every configuration once per round (default 7)")
    parser.add_argument("--updates", type=int, default=3, help="updates per configuration per round (default 3)")
    parser.add_argument("--warmup", type=int, default=2, help="untimed updates per configuration first (default 2)")
    parser.add_argument("--frames", type=int, default=600, help="simulator frames to measure JPEG size on (default 600)")
    parser.add_argument("--only", default="", help="comma-separated configuration names (default: all of "
                                                   + ", ".join(CONFIGURATIONS) + ")")
    parser.add_argument("--out", type=Path, help="also write option_costs.json and option_costs.md into this folder")
    add_config_arguments(parser)
    args, config = parse_config_or_exit(parser, argv)
    names = [name.strip() for name in args.only.split(",") if name.strip()] or list(CONFIGURATIONS)
    unknown = sorted(set(names) - set(CONFIGURATIONS))
    if unknown:
        parser.error(f"unknown configurations {unknown}; choose from {list(CONFIGURATIONS)}")
    torch.set_num_threads(args.threads)
    configs = {name: load_config(base=config, overrides=CONFIGURATIONS[name][1]) for name in names}
    header = (f"CPU: {describe_cpu()}; torch {torch.__version__}, {args.threads} thread(s); {args.rounds} rounds x "
              f"{args.updates} updates after {args.warmup} warm-up; LSTM {config.network.lstm_units}, frames "
              f"{config.network.frame_height}x{config.network.frame_width}")
    print(f"measuring {', '.join(names)}", file=sys.stderr, flush=True)
    frame = frame_bytes(config, args.frames)
    rows = table(configs, measure(configs, args.rounds, args.updates, args.warmup), frame)
    text = markdown(rows, header)
    print(text, flush=True)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "option_costs.json").write_text(json.dumps({"header": header, "rows": rows}, indent=2) + "\n")
        (args.out / "option_costs.md").write_text(text)


if __name__ == "__main__":
    main()
