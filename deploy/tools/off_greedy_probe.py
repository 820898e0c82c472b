"""How often each fixed action rule would leave argmax Q, on the states a policy drives through greedily.

Softmax at kappa 0.1 and Max-Boltzmann (epsilon 0.05 of such samples) explore as much as the gaps between
a network's Q-values let them: where the best two actions lie 0.05 apart, a softmax(Q / 0.1) sample is
another action about four times in ten. The probe drives the policy greedily from the first --starts train
starts (the evaluation's simulator, float32 network, LSTM state zeroed per start) for up to --steps steps
each and reads, at every step, the chance that each rule of the run's config takes another action than
argmax Q:

    softmax        1 - max softmax(Q / kappa)                    (exploration.softmax.kappa)
    max_boltzmann  epsilon * (1 - max softmax(Q / kappa))        (exploration.max_boltzmann)
    constant       epsilon * (n - 1) / n, a uniform draw         (exploration.constant.epsilon)

with the median gap between the best and second Q-value. The actors count the same thing live
(EpisodeRecord.off_greedy) on their own, exploring trajectories; this reads a kept policy after the fact.

    .venv/bin/python deploy/tools/off_greedy_probe.py runs/grid/mbe/policies/policy-u0028000.pt --starts 3 --steps 400
    .venv/bin/python deploy/tools/off_greedy_probe.py POLICY --exploration.softmax.kappa 0.5   # another temperature
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from actor.batched_q import BatchedQ
from actor.evaluation import EvaluationError
from actor.evaluation.episodes import evaluation_env_config
from actor.evaluation.sources import checkpoint_source
from actor.lockstep import Lockstep
from actor.sim import make_env, start_poses
from common.checkpoint import CheckpointError
from common.config import Config
from common.config_cli import add_config_arguments, parse_flags
from common.exploration.base import softmax_probabilities
from common.network import D3RQN, load_numpy_weights
from common.schema.fields import ConfigError


def rule_off_greedy(q_rows: np.ndarray, epsilon: float, kappa: float) -> float:
    """The mean over rows of the chance that the rule (epsilon of softmax(Q / kappa) samples; kappa 0: of
    uniform draws) takes another action than argmax Q."""
    q_rows = np.asarray(q_rows, dtype=np.float64)
    if kappa == 0:
        return epsilon * (q_rows.shape[1] - 1) / q_rows.shape[1]
    return epsilon * float(np.mean([1.0 - softmax_probabilities(row, kappa).max() for row in q_rows]))


def greedy_q_rows(config: Config, weights: dict[str, np.ndarray], starts: int, steps: int) -> np.ndarray:
    """(steps driven, n_actions): the float32 network's Q-values along its greedy drives from train starts."""
    network = D3RQN(config.network)
    load_numpy_weights(network, weights)
    q = BatchedQ(network, 1)
    core = Lockstep([make_env(evaluation_env_config(config), seed=config.evaluation.seed)], steps, keep_frames=False)
    rows = []
    for start in range(starts):
        drive = core.begin(0, options={"start_set": "train", "start_index": start})
        q.reset(0)
        while 0 in core.running:  # until the simulator ends the drive, or `steps` of it
            values = q.q_values([0], [drive.observation])[0].numpy()
            rows.append(values)
            core.step({0: int(np.argmax(values))})
    core.envs[0].close()
    return np.asarray(rows, dtype=np.float64)


def report(config: Config, rows: np.ndarray) -> list[str]:
    exploration = config.exploration
    ranked = np.sort(rows, axis=1)
    rules = (("softmax", 1.0, exploration.softmax.kappa),
             ("max_boltzmann", exploration.max_boltzmann.epsilon, exploration.max_boltzmann.kappa),
             ("constant", exploration.constant.epsilon, 0.0))
    return [f"{len(rows):,d} greedy steps; Q-values: mean {rows.mean():.2f}, median gap best to second "
            f"{np.median(ranked[:, -1] - ranked[:, -2]):.3f}",
            *(f"{name:<14} epsilon {epsilon:g}, kappa {kappa:g}: another action than argmax Q "
              f"{100 * rule_off_greedy(rows, epsilon, kappa):.2f}% of steps" for name, epsilon, kappa in rules)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="deploy/tools/off_greedy_probe.py", description=__doc__.splitlines()[0])
    parser.add_argument("policy", type=Path, help="a kept or shipped policy, a checkpoint, or a run folder")
    parser.add_argument("--starts", type=int, default=3, help="train starts driven from, the first N (default 3)")
    parser.add_argument("--steps", type=int, default=400, help="the most steps driven from each (default 400)")
    add_config_arguments(parser)  # the policy's config, changed only by --config FILE and the flags given
    args = parse_flags(parser, argv)
    torch.set_num_threads(1)
    try:
        if not 1 <= args.starts <= len(start_poses("train")) or args.steps < 1:
            raise ConfigError(f"--starts must lie in 1..{len(start_poses('train'))} (the train set) and --steps be >= 1")
        source = checkpoint_source(args.policy, args)
        config = source.config
        rows = greedy_q_rows(config, source.weights, args.starts, args.steps)
    except (CheckpointError, ConfigError, EvaluationError, ValueError) as error:
        print(f"off_greedy_probe: error: {error}", file=sys.stderr)
        return 1
    print("\n".join(report(config, rows)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
