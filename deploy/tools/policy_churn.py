"""Policy churn: how much the greedy action changes between a run's kept policies, beside how much their curve moves.

A greedy curve that swings by 20 points of CFR between policies kept 2,000 updates apart can be the policy
changing (churn: the greedy action flips in many states within a few updates, Schaul et al. 2022, "The
phenomenon of policy churn") or the evaluation's noise at K = 5 trials per start. This tool measures the first
directly. It drives the map-reading driver (actor/sim/privileged.py, the evaluation's simulator) from every
test start, trial 0's seed, for up to --steps steps: a fixed set of states, the same for every policy. Each
kept policy of each kind then reads those frames from a zero LSTM state, start by start (the evaluation's
float32 network), and takes its argmax Q at every step. For each pair of policies of a kind kept --apart
updates apart it prints the share of the states whose greedy action differs, next to the change of their
greedy test CFR on the run's curve (curve/curve.csv, where it has both), and writes churn.csv:

    .venv/bin/python deploy/tools/policy_churn.py runs/grid/bmc-b1000-s0
    .venv/bin/python deploy/tools/policy_churn.py runs/grid2/bmc-b2000-s0 --kinds online,target,ema --from-updates 20000

Reading it: the states are the driver's, not the policy's own, so a flip counts wherever the policy would be
asked, on the road it is meant to keep; churn near 0 between neighbours whose CFR moves by tens of points says
the curve's swing is the evaluation's noise; churn of several percent says the policy itself moves.
"""

from __future__ import annotations

import argparse
import csv
import statistics
import sys
from pathlib import Path

import numpy as np
import torch
from scipy.stats import spearmanr

from actor.evaluation import EvaluationError
from actor.evaluation.curve import CURVE_CSV, read_curve
from actor.evaluation.episodes import (EpisodeJob, PrivilegedPolicy, choose_actions, evaluation_env_config,
                                       trial_seed)
from actor.evaluation.sources import check_weights
from actor.lockstep import Lockstep
from actor.sim import make_env, start_poses
from common.checkpoint import CheckpointError, KeptPolicy
from common.config import Config
from common.config_values import from_dict
from common.eta import Eta
from common.network import D3RQN, load_numpy_weights
from common.schema.fields import ConfigError
from common.run_dir import POLICY_KINDS, RunDir

CHURN_CSV = "churn.csv"
COLUMNS = ("kind", "updates", "next_updates", "churn", "states", "test_cfr", "next_test_cfr", "cfr_change")
DEFAULT_STEPS = 300
DEFAULT_APART = 1_000


def probe_frames(config: Config, steps: int, start_set: str = "test") -> list[np.ndarray]:
    """The frames the map-reading driver sees from each start of a set (trial 0's seed), one (T, H, W, C)
    array a start, the frames it acted on: at most `steps`, fewer where its episode ended sooner."""
    env_config = evaluation_env_config(config)
    count = len(start_poses(start_set))
    envs = [make_env(env_config) for _ in range(count)]
    try:
        core, driver = Lockstep(envs, steps, keep_frames=True), PrivilegedPolicy(env_config, count)
        jobs = {}
        for index in range(count):
            job = EpisodeJob("privileged", start_set, index, 0, trial_seed(config.evaluation.seed, start_set, index, 0))
            core.begin(index, seed=job.seed, options={"start_set": start_set, "start_index": index})
            driver.begin(index, job, envs[index].unwrapped.pose)
            jobs[index] = job
        frames: dict[int, np.ndarray] = {}
        while core.running:
            for slot, trajectory in core.step(choose_actions(core, jobs, {"privileged": driver})):
                frames[slot] = np.stack(trajectory.frames[:trajectory.length])
        return [frames[index] for index in range(count)]
    finally:
        for env in envs:
            env.close()


@torch.no_grad()
def sequence_q_values(network: D3RQN, sequences: list[np.ndarray]) -> list[torch.Tensor]:
    """Q at every frame of each sequence, (T, n_actions) a sequence, each read from a zero LSTM state."""
    network.eval()
    return [network(torch.from_numpy(frames).unsqueeze(0), network.initial_state(1))[0][0] for frames in sequences]


def greedy_actions(network: D3RQN, sequences: list[np.ndarray]) -> np.ndarray:
    """argmax Q at every frame of every sequence; all sequences end to end."""
    return np.concatenate([q_values.argmax(dim=-1).numpy() for q_values in sequence_q_values(network, sequences)])


def churn(first: np.ndarray, second: np.ndarray) -> float:
    """The share of the states whose greedy action differs between two policies."""
    if first.shape != second.shape or not first.size:
        raise ValueError(f"greedy actions over other states: {first.shape} and {second.shape}")
    return float(np.mean(first != second))


def pairs(updates: list[int], apart: int) -> list[tuple[int, int]]:
    """The pairs of kept policies exactly `apart` updates apart, by the earlier one."""
    kept = set(updates)
    return [(early, early + apart) for early in sorted(kept) if early + apart in kept]


def test_cfr(rows: list[dict]) -> dict[int, float]:
    return {int(row["updates"]): float(row["cfr"]) for row in rows if row["start_set"] == "test"}


def churn_rows(run: RunDir, kinds: list[str], sequences: list[np.ndarray], apart: int, from_updates: int,
               network_of) -> list[dict]:
    """A row per pair of each kind's kept policies `apart` updates apart, from `from_updates` on."""
    curve = run.curve / CURVE_CSV
    rows = []
    for kind in kinds:
        kept = {updates: path for updates, path in run.kept_policies(kind) if updates >= from_updates}
        cfr = test_cfr(read_curve(curve, kind)) if curve.is_file() else {}
        wanted = pairs(list(kept), apart)
        needed = sorted({updates for pair in wanted for updates in pair})
        actions, eta = {}, Eta(len(needed))
        for number, updates in enumerate(needed, 1):
            actions[updates] = greedy_actions(network_of(kept[updates]), sequences)
            eta.update(number)
            print(f"churn: {kind} {number}/{len(needed)} policies read, ETA {eta.text()}", file=sys.stderr, flush=True)
        for early, late in wanted:
            change = cfr[late] - cfr[early] if early in cfr and late in cfr else None
            rows.append({"kind": kind, "updates": early, "next_updates": late,
                         "churn": churn(actions[early], actions[late]), "states": actions[early].size,
                         "test_cfr": cfr.get(early), "next_test_cfr": cfr.get(late), "cfr_change": change})
    return rows


def policy_network(path: Path) -> D3RQN:
    policy = KeptPolicy.load(path)
    config = from_dict(policy.config)
    weights = policy.weights()
    check_weights(config, weights)
    network = D3RQN(config.network)
    load_numpy_weights(network, weights)
    return network


def write_rows(path: Path, rows: list[dict]) -> None:
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows({key: "" if value is None else value for key, value in row.items()} for row in rows)


def summary_lines(rows: list[dict]) -> list[str]:
    """Per kind: the median churn, the median |CFR change| and their rank correlation across the pairs."""
    lines = []
    for kind in dict.fromkeys(row["kind"] for row in rows):
        of_kind = [row for row in rows if row["kind"] == kind]
        paired = [row for row in of_kind if row["cfr_change"] is not None]
        line = (f"{kind}: {len(of_kind)} pairs, churn median {100 * statistics.median(r['churn'] for r in of_kind):.1f}% "
                f"(range {100 * min(r['churn'] for r in of_kind):.1f}-{100 * max(r['churn'] for r in of_kind):.1f}%)")
        if len(paired) >= 3:
            rho = spearmanr([r["churn"] for r in paired], [abs(r["cfr_change"]) for r in paired]).statistic
            line += (f"; |test CFR change| median {100 * statistics.median(abs(r['cfr_change']) for r in paired):.0f} "
                     f"points over {len(paired)} pairs on the curve, Spearman rho(churn, |change|) {rho:.2f}")
        lines.append(line)
    return lines


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="deploy/tools/policy_churn.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a run folder with kept policies (policies/)")
    parser.add_argument("--kinds", default="online", help=f"kinds of kept policy, of {', '.join(POLICY_KINDS)} "
                                                          "(default: online)")
    parser.add_argument("--apart", type=int, default=DEFAULT_APART, help="updates between the policies of a pair "
                                                                        f"(default {DEFAULT_APART:,d})")
    parser.add_argument("--from-updates", type=int, default=0, help="only policies kept at this many updates or later")
    parser.add_argument("--steps", type=int, default=DEFAULT_STEPS,
                        help=f"steps of the driver from each test start (default {DEFAULT_STEPS})")
    parser.add_argument("--out", type=Path, help=f"the CSV to write (default: <run>/curve/{CHURN_CSV})")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    kinds = [kind.strip() for kind in args.kinds.split(",") if kind.strip()]
    try:
        if not kinds or any(kind not in POLICY_KINDS for kind in kinds):
            raise EvaluationError(f"--kinds: choose from {', '.join(POLICY_KINDS)}, got {args.kinds!r}")
        if args.apart < 1 or args.steps < 1:
            raise EvaluationError("--apart and --steps must be at least 1")
        run = RunDir(args.run)
        kept = run.kept_policies(kinds[0])
        if not kept:
            raise EvaluationError(f"no kept {kinds[0]} policies in {run.policy_folder(kinds[0])}/")
        config = from_dict(KeptPolicy.load(kept[-1][1]).config)
        sequences = probe_frames(config, args.steps)
        rows = churn_rows(run, kinds, sequences, args.apart, args.from_updates, policy_network)
    except (CheckpointError, ConfigError, EvaluationError, ValueError) as error:
        print(f"policy_churn: error: {error}", file=sys.stderr)
        return 1
    if not rows:
        print(f"policy_churn: no two kept policies {args.apart:,d} updates apart in {args.run}", file=sys.stderr)
        return 1
    out = args.out or run.curve / CHURN_CSV
    out.parent.mkdir(parents=True, exist_ok=True)
    write_rows(out, rows)
    for row in rows:
        change = "" if row["cfr_change"] is None else f", test CFR {100 * row['cfr_change']:+.0f} points"
        print(f"{row['kind']} {row['updates']:,d} -> {row['next_updates']:,d}: churn {100 * row['churn']:.1f}% of "
              f"{row['states']:,d} states{change}")
    print("\n".join(summary_lines(rows)))
    print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
