"""The mean of several kept policies' weights: one policy that smooths the swing between neighbouring ones.

    .venv/bin/python deploy/tools/average_policies.py runs/bmc --last 5 --out runs/bmc/averaged/last5.pt
    .venv/bin/python deploy/tools/average_policies.py runs/bmc/policies/policy-u0079000.pt \\
        runs/bmc/policies/policy-u0080000.pt --out runs/bmc/averaged/two.pt

Beyond the paper, and outside training: nothing the learner does changes. A greedy curve swings by hundreds
of steps between policies kept 1,000 updates apart (test CFR 30-92% at K = 5 among the long run's policies
past 24,000 updates) while the weights move little. Their mean along one run is Polyak averaging (Polyak and
Juditsky 1992; stochastic weight averaging, Izmailov et al. 2018, which Nikishin et al. 2018 applied to DQN).
The learner's target network is the same idea over about 1/tau = 1,000 updates.

A run folder stands for its last --last kept policies. Every policy must rebuild the same network (the
network section of their configs) and hold the same tensors; 16-bit (shipped) weights are widened first.
The file written is a kept policy in float32 with the updates, env steps, wall time, CPU and config of the
latest of them, and the updates of all it averages (KeptPolicy.averaged), which `evaluate --checkpoint`
prints. Do not write it into a run's policies/: the curve would read it as the policy the learner kept.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import torch

from actor.evaluation import EvaluationError
from actor.evaluation.sources import check_weights
from common.checkpoint import CheckpointError, KeptPolicy
from common.config_values import from_dict
from common.schema.fields import ConfigError
from common.run_dir import RunDir

DEFAULT_LAST = 5


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="deploy/tools/average_policies.py",
        description="Writes the mean of several kept policies' weights (of one network) as a kept policy that "
                    "evaluate --checkpoint reads. Beyond the paper: the learner is not changed.")
    parser.add_argument("sources", type=Path, nargs="+", metavar="PATH",
                        help="kept policies (policies/policy-u<updates>.pt or shipped ones), or a run folder "
                             "(its last --last kept policies)")
    parser.add_argument("--last", type=int, default=DEFAULT_LAST, metavar="N",
                        help=f"how many of a run folder's last kept policies to average (default {DEFAULT_LAST})")
    parser.add_argument("--out", type=Path, required=True, metavar="FILE",
                        help="the file to write (.pt); not in a run's policies/ folder")
    return parser


def policy_files(sources: list[Path], last: int) -> list[Path]:
    """The policy files: each file as given, each run folder's last `last` kept policies."""
    if last < 1:
        raise CheckpointError(f"--last must be at least 1, not {last}")
    files = []
    for source in sources:
        if source.is_dir():
            kept = RunDir(source).kept_policies()
            if not kept:
                raise CheckpointError(f"{source} holds no kept policies (policies/policy-u<updates>.pt)")
            files += [path for _, path in kept[-last:]]
        else:
            files.append(source)
    return files


def average(policies: list[KeptPolicy]) -> KeptPolicy:
    """The mean, tensor by tensor in float32, of policies of one network, dated as the latest of them."""
    if len(policies) < 2:
        raise CheckpointError("averaging takes at least two policies")
    first = policies[0]
    for policy in policies:
        if policy.averaged or policy.kind != "online":
            raise CheckpointError(f"{policy.path} is a {policy.kind} policy: the mean is of kept online policies")
        if policy.config.get("network") != first.config.get("network"):
            raise CheckpointError(f"{policy.path} is of another network than {first.path} (their configs' "
                                  "network sections differ)")
        shapes = {name: tuple(tensor.shape) for name, tensor in policy.online.items()}
        if shapes != {name: tuple(tensor.shape) for name, tensor in first.online.items()}:
            raise CheckpointError(f"{policy.path} holds other tensors than {first.path}")
    mean = {name: torch.stack([policy.online[name].float() for policy in policies]).mean(dim=0)
            for name in first.online}
    latest = max(policies, key=lambda policy: policy.updates)
    updates = tuple(sorted(policy.updates for policy in policies))
    return dataclasses.replace(latest, online=mean, averaged=updates, kind="mean", path=None)


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    try:
        if args.out.resolve().parent.name == "policies":
            raise CheckpointError(f"{args.out} lies in a policies/ folder, where the curve would take it for a "
                                  "policy the learner kept")
        policies = [KeptPolicy.load(path) for path in policy_files(args.sources, args.last)]
        mean = average(policies)
        check_weights(from_dict(mean.config), mean.weights())
        args.out.parent.mkdir(parents=True, exist_ok=True)
        mean.save(args.out)
    except (CheckpointError, ConfigError, EvaluationError) as error:
        print(f"average_policies: error: {error}", file=sys.stderr)
        raise SystemExit(1) from None
    print(f"wrote {args.out}: the mean of {len(policies)} kept policies' weights, updates "
          f"{', '.join(f'{updates:,}' for updates in mean.averaged)}; dated as updates {mean.updates:,}, "
          f"env steps {mean.env_steps:,}")


if __name__ == "__main__":
    main()
