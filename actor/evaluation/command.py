"""`evaluate`, the command line of actor/evaluation/: the greedy policy of a checkpoint, or of the live
learner, on the paper's protocol.

Greedy actions (argmax Q, LSTM state zeroed at every episode start),
``evaluation.episodes_per_start`` trials from each of the 10 start poses of
the train set and of the test set, episodes capped at ``evaluation.max_steps``.
Episodes are spread over ``evaluation.workers`` processes (multiprocessing,
'spawn'), each stepping ``evaluation.envs_per_worker`` simulators in lockstep
with one batched forward pass per step (actor/evaluation/episodes.py). A
uniformly random policy, and on request the privileged map-reading driver
(and the same driver turning right wherever it can, which loops), run the
same starts for comparison. Results go to ``--out`` (default: the
run folder's evaluation folder, common/run_dir.py): episodes.csv, summary.csv, summary.md, facts.json,
config.toml. Mean and IQM length, CFR, progress, the streets and junctions
visited and reward per step come with
confidence intervals (common/analysis/intervals.py); from one checkpoint they
show the spread of the trials only, not that of other training runs.

    evaluate --checkpoint runs/bmc                 # the run's latest checkpoint
    evaluate --checkpoint backup/bmc-early.pt --evaluation.workers 2
    evaluate --live --run.name bmc --transport.mode client --transport.connect tcp/127.0.0.1:7447
    evaluate --curve runs/bmc --nice 10            # every policy the run kept (actor/evaluation/curve.py)
    evaluate --curve runs/bmc --nice 15 --follow   # and those it keeps, until its stack stops training
"""

from __future__ import annotations

import argparse
import datetime
import logging
import os
import sys
import threading
import time
from pathlib import Path

from actor.evaluation import EvaluationError
from actor.evaluation.curve import (CURVE_CSV, CURVE_TRIALS, curve_config, curve_policies, evaluate_curve, read_curve,
                                    summary_lines, warn_if_crowding, write_outputs)
from actor.evaluation.protocol import evaluate
from actor.evaluation.sources import checkpoint_source, check_weights, live_source
from actor.evaluation.workers import worker_layout
from actor.sim import START_SETS
from common.analysis.tables import SUMMARY_MD, write_evaluation
from common.checkpoint import CheckpointError
from common.config_cli import add_config_arguments, config_from_args, parse_flags
from common.config_values import to_toml
from common.schema.fields import ConfigError
from common.run_dir import POLICY_KINDS, RunDir, RunStatus, StatusError
from common.shell import interrupt_main, run_main, stop_with_parent

FOLLOW_EVERY_S = 60.0  # --follow: how often to look for new kept policies


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="evaluate",
        description="Evaluates the greedy policy (argmax Q, LSTM state reset per episode) of a checkpoint or of "
                    "the live learner: evaluation.episodes_per_start episodes from each start pose of the "
                    "train and test sets, capped at evaluation.max_steps steps, spread over evaluation.workers "
                    "processes of evaluation.envs_per_worker lockstep simulators. Writes episodes.csv, "
                    "summary.csv, summary.md, facts.json and config.toml. With --checkpoint the config is the checkpoint's, "
                    "changed only by --config FILE and the flags given (--preset is ignored); with --curve each "
                    "kept policy's.")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--checkpoint", type=Path, metavar="PATH",
                        help="a checkpoint file, or a run folder (uses its latest checkpoint)")
    source.add_argument("--live", action="store_true",
                        help="ask the running learner of run.name for its latest weights (transport.* settings)")
    source.add_argument("--curve", type=Path, metavar="RUN",
                        help="the greedy learning curve of a run folder: every policy it kept (learner.keep_every) "
                             f"not yet in the curve, greedy only, {CURVE_TRIALS} trials per start unless "
                             "--evaluation.episodes_per_start says; writes curve.csv, curve.png, "
                             "curve_summary.json and .md (the time to drive)")
    parser.add_argument("--follow", type=float, nargs="?", const=FOLLOW_EVERY_S, metavar="SECONDS",
                        help="with --curve, beside a training run: evaluate the policies it keeps as they come, "
                             f"looking every SECONDS (default {FOLLOW_EVERY_S:g}), until its stack stops training "
                             "(then once more, for the policy it stops with); give it --nice")
    parser.add_argument("--from-updates", type=int, default=0, metavar="N",
                        help="with --curve, only the policies kept at N updates or later, e.g. the train rows of "
                             "a run's last policies, to choose one on the train starts (default: 0, all)")
    parser.add_argument("--to-updates", type=int, default=None, metavar="N",
                        help="with --curve, only the policies kept at N updates or earlier, e.g. a dense early "
                             "part of a curve read more sparsely later (default: no end)")
    parser.add_argument("--every", type=int, default=1, metavar="N",
                        help="with --curve, only the policies kept at multiples of N updates, e.g. 5000 on a long "
                             "run whose greedy episodes reach the cap and take minutes each (default: 1, all)")
    parser.add_argument("--out", type=Path, metavar="DIR",
                        help="output directory (default: <run dir>/evaluation, with --curve <run dir>/curve)")
    parser.add_argument("--nice", type=int, default=0, metavar="N",
                        help="lower the priority of this evaluation and its workers by N (os.nice), e.g. 10 beside "
                             "a training run; the output names the niceness it ran at (default: 0)")
    parser.add_argument("--sets", default=",".join(START_SETS), metavar="train,test",
                        help="start sets to evaluate on (default: train,test)")
    parser.add_argument("--kinds", default="online", metavar="online,target,ema",
                        help="with --curve, the kinds of kept policy to read (their rows are told apart by the "
                             f"CSV's kind column): {', '.join(POLICY_KINDS)} (default: online; the others are "
                             "beyond the paper: learner.keep_target, learner.ema_updates)")
    parser.add_argument("--random-baseline", action=argparse.BooleanOptionalAction, default=True,
                        help="also run a uniformly random policy from the same starts (default: on)")
    parser.add_argument("--privileged", action="store_true",
                        help="also run the privileged map-reading driver, an upper bound (long episodes)")
    parser.add_argument("--right-turns", action="store_true",
                        help="also run the map-reading driver turning right wherever it can: it goes round one "
                             "loop of the grid, full length over few streets, the reference for the coverage "
                             "columns (long episodes)")
    add_config_arguments(parser)
    return parser


def parse_sets(text: str) -> list[str]:
    sets = [part.strip() for part in text.split(",") if part.strip()]
    unknown = [name for name in sets if name not in START_SETS]
    if not sets or unknown:
        raise EvaluationError(f"--sets: choose from {', '.join(START_SETS)}, got {text!r}")
    return sets


def parse_kinds(text: str) -> list[str]:
    kinds = [part.strip() for part in text.split(",") if part.strip()]
    unknown = [name for name in kinds if name not in POLICY_KINDS]
    if not kinds or unknown or len(set(kinds)) < len(kinds):
        raise EvaluationError(f"--kinds: choose from {', '.join(POLICY_KINDS)}, each once, got {text!r}")
    return kinds


def main(argv: list[str] | None = None) -> None:
    args = parse_flags(build_parser(), argv)
    stop_with_parent(threading.Event(), then=interrupt_main)  # started by a grid runner or main job that asked
    try:
        _main(args)
    except (EvaluationError, ConfigError, CheckpointError) as error:
        print(f"evaluate: error: {error}", file=sys.stderr)
        raise SystemExit(1) from None
    except KeyboardInterrupt:
        kept = "; the curve keeps the policies evaluated so far" if args.curve else ", nothing written"
        print(f"\nevaluate: interrupted{kept}", file=sys.stderr)
        raise SystemExit(130) from None


def lower_priority(steps: int) -> int:
    """Lowers this process's priority (its workers inherit it) by `steps`; returns the niceness it now runs at."""
    if steps < 0:
        raise EvaluationError(f"--nice: must be >= 0 (raising a priority needs root), got {steps}")
    return os.nice(steps)


def _main(args: argparse.Namespace) -> None:
    sets = parse_sets(args.sets)
    nice = lower_priority(args.nice)
    if args.curve is not None:
        _curve(args, sets, nice)
        return
    source = checkpoint_source(args.checkpoint, args) if args.checkpoint is not None else None
    config = source.config if source is not None else config_from_args(args)
    if args.dump_config:
        print(to_toml(config), end="")
        return
    source = source if source is not None else live_source(config)
    check_weights(config, source.weights)
    policies = ["greedy", *(["random"] if args.random_baseline else []), *(["privileged"] if args.privileged else []),
                *(["right-turns"] if args.right_turns else [])]
    started = time.monotonic()
    episodes, summaries = evaluate(config, source.weights, policies, sets)
    wall_s = time.monotonic() - started
    out_dir = args.out if args.out is not None else source.run_dir.evaluation
    evaluation = config.evaluation
    workers, simulators, threads = worker_layout(evaluation, len(episodes))
    facts = {**source.facts,
             "protocol": f"{evaluation.episodes_per_start} episodes from each start of {', '.join(sets)}, "
                         f"capped at {evaluation.max_steps} steps; greedy = argmax Q",
             "seed": str(evaluation.seed),
             "intervals": f"{100 * evaluation.confidence:g}% percentile intervals of {evaluation.bootstrap_replicates} "
                          "bootstrap replicates (trials resampled within each start)",
             "processes": f"{workers} worker(s) x {simulators} lockstep env(s), {threads} torch thread(s) each",
             "wall time": f"{wall_s:.1f} s",
             "priority": f"nice {nice}",
             "date": datetime.datetime.now().isoformat(timespec="seconds")}
    paths = write_evaluation(out_dir, episodes, summaries, evaluation.reward_bins, facts, evaluation.episodes_per_start,
                             to_toml(config), evaluation.confidence)
    print((out_dir / SUMMARY_MD).read_text())
    print("wrote " + ", ".join(str(path) for path in paths), file=sys.stderr)


def _curve(args: argparse.Namespace, sets: list[str], nice: int) -> None:
    if args.dump_config:
        raise EvaluationError("--dump-config does not apply to --curve: each kept policy has its own config")
    config_from_args(args)  # a bad flag is one error here, not every kept policy skipped
    logging.basicConfig(format="evaluate: %(levelname)s %(message)s")  # the log lines of skipped files
    run = RunDir(args.curve)
    out_dir = args.out if args.out is not None else run.curve
    if args.follow is not None and args.follow <= 0:
        raise EvaluationError(f"--follow: seconds must be > 0, got {args.follow:g}")
    if args.every < 1:
        raise EvaluationError(f"--every: updates must be >= 1, got {args.every}")
    kinds = parse_kinds(args.kinds)
    if args.follow is not None:
        warn_if_crowding(run, args)
    while True:
        training = args.follow is not None and _stack_training(run)
        if args.follow is not None and not any(curve_policies(run.kept_policies(kind), args.from_updates,
                                                              args.every, args.to_updates) for kind in kinds):
            if training:
                time.sleep(args.follow)  # none kept yet that the curve reads
                continue
            print("curve: the run stopped before keeping a policy in this span at such a multiple: nothing to "
                  "follow", file=sys.stderr)  # a budget shorter than --every, say; the run is no worse for it
            return
        rows = evaluate_curve(run, out_dir, sets, lambda saved: curve_config(saved, args), nice,
                              from_updates=args.from_updates, every=args.every, to_updates=args.to_updates,
                              kinds=kinds)
        evaluated_now = rows is not None
        if rows is None and not training:
            rows = read_curve(out_dir / CURVE_CSV, kind=None) or None  # nothing new: redrawn whole
        if rows is not None:
            summary, paths = write_outputs(out_dir, rows, run.root.name, evaluated_now)
            print("\n".join(summary_lines(summary)))
            print("wrote " + ", ".join(str(path) for path in paths), file=sys.stderr)
        if not training:
            return
        time.sleep(args.follow)


def _stack_training(run: RunDir) -> bool:
    try:
        return RunStatus.read(run.status).training()
    except StatusError as error:  # written atomically, so missing or damaged: no stack to follow
        print(f"curve: no stack to follow ({error})", file=sys.stderr)
        return False


if __name__ == "__main__":
    run_main(main)
