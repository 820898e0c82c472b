"""A trained policy small enough to ship with the project: the online weights only, in 16 bits.

    .venv/bin/python deploy/tools/ship_policy.py runs/bmc/policies/policy-u0021000.pt --out results/bmc/policy.pt
    .venv/bin/python deploy/tools/ship_policy.py runs/bmc --out results/bmc/policy.pt --encoding bfloat16

The source is a kept policy (<run>/policies/policy-u<updates>.pt), a learner checkpoint or a run folder (its
latest checkpoint). The file written is a kept policy (KeptPolicy, common/checkpoint.py): the run's config,
which rebuilds the network, the updates, env steps and wall time it was kept at, and the online weights, in
float16 (the default) or bfloat16: 24.3 MB at the paper's sizes against 48.6 MB in float32.
`evaluate --checkpoint FILE`, `deploy/tools/animate_policy.py --checkpoint FILE` and `evaluate --curve` (as a
file of a run's policies/) read it and widen the weights to float32, exactly, on any CPU.

float16 by default: a trained network's weights lie far inside its range (+-65,504; a weight beyond it is
refused, naming the tensor), and its 11-bit significand rounds 8 times finer than bfloat16's 8 bits; on the
main job's networks float16 weights moved the Q-values about 10 times less than bfloat16 weights and changed
0-0.03% of the greedy actions against 0.10-0.18% (docs/architecture.md, "What a compact encoding changes").
bfloat16 keeps float32's range, for a network whose weights float16 cannot hold.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from actor.evaluation import EvaluationError
from actor.evaluation.sources import check_weights
from common.checkpoint import POLICY_ENCODINGS, CheckpointError, KeptPolicy, load_checkpoint_or_policy
from common.config_values import from_dict
from common.schema.fields import ConfigError

ENCODINGS = [name for name in POLICY_ENCODINGS if name != "float32"]
MB = 1e6


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="deploy/tools/ship_policy.py",
        description="Writes a policy's online weights in 16 bits, with its run's config and the updates and env "
                    "steps it was kept at: a file evaluate --checkpoint reads, half the size of a kept policy.")
    parser.add_argument("source", type=Path, metavar="PATH",
                        help="a kept policy (policies/policy-u<updates>.pt), a checkpoint file, or a run folder "
                             "(its latest checkpoint)")
    parser.add_argument("--out", type=Path, required=True, metavar="FILE", help="the file to write (.pt)")
    parser.add_argument("--encoding", choices=ENCODINGS, default="float16",
                        help="float16 (default: 8x finer rounding) or bfloat16 (float32's range)")
    return parser


def source_policy(path: Path) -> KeptPolicy:
    """The float32 policy a kept policy file, a checkpoint or a run folder holds, checked against its config."""
    saved = load_checkpoint_or_policy(path)
    policy = saved if isinstance(saved, KeptPolicy) else KeptPolicy.of_checkpoint(saved)
    if policy.encoding != "float32":
        raise CheckpointError(f"{policy.path} holds {policy.encoding} weights already (a shipped policy, or one "
                              "kept with learner.keep_encoding): copy it as it is, or ship from a float32 kept "
                              "policy or checkpoint")
    check_weights(from_dict(policy.config), policy.weights())
    return policy


def ship(policy: KeptPolicy, out: Path, encoding: str) -> KeptPolicy:
    """Writes the policy in `encoding` to `out`, checked by reading it back; returns what was read."""
    compact = policy.compact(encoding)
    shipped = KeptPolicy.load(compact.save(out))
    if any(not torch.equal(shipped.online[name], tensor) for name, tensor in compact.online.items()):
        raise CheckpointError(f"{out} does not read back as written")
    return shipped


def rounding(policy: KeptPolicy, shipped: KeptPolicy) -> tuple[float, float]:
    """The largest |weight| of the float32 policy, and the largest change the rounding made to one."""
    largest = max(tensor.abs().max().item() for tensor in policy.online.values())
    change = max((shipped.online[name].float() - tensor.float()).abs().max().item()
                 for name, tensor in policy.online.items())
    return largest, change


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    try:
        policy = source_policy(args.source)
        shipped = ship(policy, args.out, args.encoding)
    except (CheckpointError, ConfigError, EvaluationError) as error:
        print(f"ship_policy: error: {error}", file=sys.stderr)
        raise SystemExit(1) from None
    largest, change = rounding(policy, shipped)
    full = sum(tensor.numel() * 4 for tensor in policy.online.values())
    print(f"{policy.path}: updates {policy.updates:,}, env steps {policy.env_steps:,}")
    print(f"wrote {args.out}: {args.encoding} weights, {args.out.stat().st_size / MB:.1f} MB "
          f"(the weights in float32: {full / MB:.1f} MB)")
    limit = torch.finfo(POLICY_ENCODINGS[args.encoding]).max
    print(f"largest |weight| {largest:.4g} ({args.encoding} holds up to {limit:.6g}); "
          f"largest rounding change {change:.3g}")


if __name__ == "__main__":
    main()
