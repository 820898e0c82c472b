"""`evaluate`: the greedy policy of a checkpoint, or of the live learner, on the paper's protocol.

Greedy actions (argmax Q, LSTM state zeroed at every episode start),
``evaluation.episodes_per_start`` trials from each of the 10 start poses of
the train set and of the test set, episodes capped at ``evaluation.max_steps``.
Episodes are spread over ``evaluation.workers`` processes (multiprocessing,
'spawn'), each stepping ``evaluation.envs_per_worker`` simulators in lockstep
with one batched forward pass per step (actor/evaluation_episodes.py). A
uniformly random policy, and on request the privileged map-reading driver,
run the same starts for comparison. Results go to ``--out`` (default
``<run dir>/evaluation/``): episodes.csv, summary.csv, summary.md, facts.json,
config.toml. Mean and IQM length, CFR, progress and reward per step come with
confidence intervals (actor/evaluation_intervals.py); from one checkpoint they
show the spread of the trials only, not that of other training runs.

    evaluate --checkpoint runs/bmc                 # the run's checkpoints/latest.pt
    evaluate --checkpoint runs/bmc/checkpoints/latest.pt --evaluation.workers 2
    evaluate --live --run.name bmc --transport.mode client --transport.connect tcp/127.0.0.1:7447
"""

from __future__ import annotations

import argparse
import datetime
import multiprocessing
import os
import queue
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence, TextIO

import numpy as np

from actor.evaluation_episodes import (EpisodeJob, WorkerDone, WorkerFailed, episode_jobs, evaluation_worker)
from actor.evaluation_intervals import Bootstrap
from actor.evaluation_report import SUMMARY_MD, write_report
from actor.evaluation_stats import EvaluationEpisode, SetSummary, summarise_all
from actor.sim import START_SETS
from common.config import Config, ConfigError, add_config_arguments, config_from_args, from_dict, parse_flags, to_toml
from common.network import D3RQN, load_numpy_weights
from common.transport import Keys, open_session, request
from common.wire import Weights
from learner.checkpoint import LATEST, CheckpointError, load_checkpoint

CHECKPOINTS_DIR = "checkpoints"  # learner/service.py writes <runs_dir>/<run>/checkpoints/latest.pt
OUTPUT_DIR = "evaluation"
WORKER_EXIT_TIMEOUT_S = 10.0
LIVE_RETRY_S = 0.2


class EvaluationError(RuntimeError):
    """The evaluation cannot run: no weights, unusable settings, or a worker failed."""


@dataclass
class PolicySource:
    """The weights to evaluate, the config they go with, and where they came from."""

    weights: dict[str, np.ndarray]
    config: Config
    run_dir: Path
    facts: dict[str, str]


# --- where the weights come from ----------------------------------------------------------------

def locate_checkpoint(path: Path) -> tuple[Path, Path]:
    """(checkpoint file, run directory) for a checkpoint file, a checkpoints directory or a run directory."""
    if path.is_file():
        return path, path.parent.parent if path.parent.name == CHECKPOINTS_DIR else path.parent
    if (path / CHECKPOINTS_DIR / LATEST).is_file():
        return path / CHECKPOINTS_DIR / LATEST, path
    if (path / LATEST).is_file():
        return path / LATEST, path.parent if path.name == CHECKPOINTS_DIR else path
    raise EvaluationError(f"no checkpoint at {path}: expected a checkpoint file, a run directory with "
                          f"{CHECKPOINTS_DIR}/{LATEST}, or a directory with {LATEST}")


def checkpoint_source(path: Path, args: argparse.Namespace) -> PolicySource:
    file, run_dir = locate_checkpoint(path)
    payload = load_checkpoint(file, ("learner", "config"))
    learner = payload["learner"]
    if not isinstance(learner, dict) or "online" not in learner:
        raise EvaluationError(f"checkpoint {file} has no online network in its learner section")
    config = checkpoint_config(payload["config"], args)
    weights = {name: tensor.detach().cpu().numpy() for name, tensor in learner["online"].items()}
    env_steps = payload.get("clock", {}).get("env_steps", "unknown")
    facts = {"source": f"checkpoint {file}", "updates": str(learner.get("updates", "unknown")),
             "env steps": str(env_steps), "strategy": config.exploration.strategy}
    return PolicySource(weights, config, run_dir, facts)


def checkpoint_config(saved: Any, args: argparse.Namespace) -> Config:
    """The checkpoint's config, then --config FILE, then the flags given (--preset does not apply)."""
    if not isinstance(saved, dict):
        raise EvaluationError("the checkpoint's config section is not a table")
    return config_from_args(args, base=from_dict(saved))


def live_source(config: Config) -> PolicySource:
    """The live learner's latest weights, asked for on the run's weights/latest key."""
    keys = Keys(config.transport.namespace, config.run.name)
    with open_session(config.transport) as session:
        reply = _latest_weights(session, keys.weights_latest, config.evaluation.live_timeout_s)
    if reply is None:
        raise EvaluationError(f"no learner answered on {keys.weights_latest} within "
                              f"{config.evaluation.live_timeout_s:g} s")
    facts = {"source": f"live learner on {keys.weights_latest}", "weights version": str(reply.version),
             "strategy": config.exploration.strategy}
    return PolicySource(dict(reply.tensors), config, Path(config.run.runs_dir) / config.run.name, facts)


def _latest_weights(session, key: str, timeout_s: float) -> Weights | None:
    """Asks until a learner answers or the time is up: a query returns at once, empty, until
    the learner is up and known to this session."""
    deadline = time.monotonic() + timeout_s
    while True:
        reply = request(session, key, None, max(deadline - time.monotonic(), LIVE_RETRY_S), expected=Weights)
        if isinstance(reply, Weights):
            return reply
        if time.monotonic() >= deadline:
            return None
        time.sleep(LIVE_RETRY_S)


def check_weights(config: Config, weights: dict[str, np.ndarray]) -> None:
    """Fails here, with the reason, rather than in every worker."""
    try:
        load_numpy_weights(D3RQN(config.network), weights)
    except ValueError as error:
        raise EvaluationError(f"the weights do not fit the configured network: {error}") from None


# --- running the episodes -------------------------------------------------------------------------

class Progress:
    """One status line: episodes done / total, episodes/s, steps/s, ETA; silent without a stream.

    On a terminal the line is rewritten in place; otherwise one line is written per period.
    """

    def __init__(self, total: int, period_s: float, stream: TextIO | None = sys.stderr, clock=time.monotonic) -> None:
        self.total, self.period_s, self.stream, self.clock = total, period_s, stream, clock
        self.started = self.shown = clock()
        self.episodes = self.steps = 0
        self.rewrite = stream is not None and stream.isatty()

    def add(self, episode: EvaluationEpisode) -> None:
        self.episodes += 1
        self.steps += episode.length
        self.tick()

    def tick(self) -> None:
        if self.clock() - self.shown >= self.period_s:
            self.show()

    def show(self, final: bool = False) -> None:
        self.shown = self.clock()
        if self.stream is None:
            return
        line = progress_line(self.episodes, self.total, self.steps, self.shown - self.started)
        end = "\n" if final or not self.rewrite else ""
        self.stream.write(("\r" if self.rewrite else "") + line + end)
        self.stream.flush()


def progress_line(done: int, total: int, steps: int, elapsed_s: float) -> str:
    rate = done / elapsed_s if elapsed_s > 0 else 0.0
    eta = _clock_time((total - done) / rate) if rate > 0 else "?"
    step_rate = steps / elapsed_s if elapsed_s > 0 else 0.0
    return (f"evaluate: {done}/{total} episodes ({100 * done / max(total, 1):.1f}%), {rate:.2f} episodes/s, "
            f"{step_rate:.0f} steps/s, elapsed {_clock_time(elapsed_s)}, ETA {eta}")


def _clock_time(seconds: float) -> str:
    minutes, second = divmod(int(round(seconds)), 60)
    hours, minute = divmod(minutes, 60)
    return f"{hours}:{minute:02d}:{second:02d}" if hours else f"{minute}:{second:02d}"


def torch_threads_per_worker(workers: int) -> int:
    return max(1, len(os.sched_getaffinity(0)) // workers)


def run_jobs(config: Config, weights: dict[str, np.ndarray] | None, jobs: Sequence[EpisodeJob],
             progress: Progress) -> list[EvaluationEpisode]:
    """Runs the jobs on min(workers, jobs) spawned processes; the episodes come back in job order."""
    context = multiprocessing.get_context("spawn")
    job_queue, result_queue = context.Queue(), context.Queue()
    n_workers = min(config.evaluation.workers, len(jobs))
    for job in jobs:
        job_queue.put(job)
    for _ in range(n_workers):
        job_queue.put(None)  # one end marker per worker
    threads = torch_threads_per_worker(n_workers)
    workers = [context.Process(target=evaluation_worker, name=f"evaluate-{number}", daemon=True,
                               args=(number, config, weights, threads, job_queue, result_queue))
               for number in range(n_workers)]
    for worker in workers:
        worker.start()
    try:
        episodes = _collect(result_queue, workers, progress)
    finally:
        for worker in workers:
            worker.join(WORKER_EXIT_TIMEOUT_S)
            if worker.is_alive():
                worker.terminate()
                worker.join()
    order = {(job.policy, job.start_set, job.start_index, job.trial): rank for rank, job in enumerate(jobs)}
    episodes.sort(key=lambda e: order[(e.policy, e.start_set, e.start_index, e.trial)])
    if len(episodes) != len(jobs):
        raise EvaluationError(f"expected {len(jobs)} episodes, the workers returned {len(episodes)}")
    return episodes


def _collect(result_queue, workers: list, progress: Progress) -> list[EvaluationEpisode]:
    episodes: list[EvaluationEpisode] = []
    finished: set[int] = set()
    while len(finished) < len(workers):
        try:
            item = result_queue.get(timeout=progress.period_s)
        except queue.Empty:
            crashed = [worker.name for worker in workers if worker.exitcode not in (None, 0)]
            if crashed:
                raise EvaluationError(f"worker(s) {', '.join(crashed)} died without a report") from None
            progress.tick()
            continue
        if isinstance(item, EvaluationEpisode):
            episodes.append(item)
            progress.add(item)
        elif isinstance(item, WorkerDone):
            finished.add(item.worker_id)
        elif isinstance(item, WorkerFailed):
            raise EvaluationError(f"worker {item.worker_id} failed:\n{item.error}")
    progress.show(final=True)
    return episodes


def evaluate(config: Config, weights: dict[str, np.ndarray] | None, policies: Sequence[str] = ("greedy", "random"),
             start_sets: Sequence[str] = START_SETS, show_progress: bool = True
             ) -> tuple[list[EvaluationEpisode], list[SetSummary]]:
    """Runs the protocol for each policy on each start set; returns the episodes and one summary row per pair."""
    edges = config.evaluation.reward_bins
    if edges[0] > 0.0 or edges[-1] < 1.0:
        raise EvaluationError(f"evaluation.reward_bins {edges} must cover [0, 1], the range of step rewards")
    if "greedy" in policies and weights is None:
        raise EvaluationError("the greedy policy needs weights")
    jobs = episode_jobs(policies, start_sets, config.evaluation.episodes_per_start, config.evaluation.seed)
    progress = Progress(len(jobs), config.evaluation.progress_period_s, sys.stderr if show_progress else None)
    episodes = run_jobs(config, weights, jobs, progress)
    return episodes, summarise_all(episodes, bootstrap_of(config))


def bootstrap_of(config: Config) -> Bootstrap:
    """The intervals' settings; the bootstrap draws from evaluation.seed, so a table is reproducible."""
    evaluation = config.evaluation
    return Bootstrap(evaluation.bootstrap_replicates, evaluation.confidence, evaluation.seed)


# --- command line ------------------------------------------------------------------------------------

def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="evaluate",
        description="Evaluates the greedy policy (argmax Q, LSTM state reset per episode) of a checkpoint or of "
                    "the live learner: evaluation.episodes_per_start episodes from each start pose of the "
                    "train and test sets, capped at evaluation.max_steps steps, spread over evaluation.workers "
                    "processes of evaluation.envs_per_worker lockstep simulators. Writes episodes.csv, "
                    "summary.csv, summary.md, facts.json and config.toml. With --checkpoint the config is the checkpoint's, "
                    "changed only by --config FILE and the flags given (--preset is ignored).")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--checkpoint", type=Path, metavar="PATH",
                        help="a checkpoint file, or a run directory (uses its checkpoints/latest.pt)")
    source.add_argument("--live", action="store_true",
                        help="ask the running learner of run.name for its latest weights (transport.* settings)")
    parser.add_argument("--out", type=Path, metavar="DIR", help="output directory (default: <run dir>/evaluation)")
    parser.add_argument("--sets", default=",".join(START_SETS), metavar="train,test",
                        help="start sets to evaluate on (default: train,test)")
    parser.add_argument("--random-baseline", action=argparse.BooleanOptionalAction, default=True,
                        help="also run a uniformly random policy from the same starts (default: on)")
    parser.add_argument("--privileged", action="store_true",
                        help="also run the privileged map-reading driver, an upper bound (long episodes)")
    add_config_arguments(parser)
    return parser


def parse_sets(text: str) -> list[str]:
    sets = [part.strip() for part in text.split(",") if part.strip()]
    unknown = [name for name in sets if name not in START_SETS]
    if not sets or unknown:
        raise EvaluationError(f"--sets: choose from {', '.join(START_SETS)}, got {text!r}")
    return sets


def main(argv: list[str] | None = None) -> None:
    args = parse_flags(build_parser(), argv)
    try:
        _main(args)
    except (EvaluationError, ConfigError, CheckpointError) as error:
        print(f"evaluate: error: {error}", file=sys.stderr)
        raise SystemExit(1) from None
    except KeyboardInterrupt:
        print("\nevaluate: interrupted, nothing written", file=sys.stderr)
        raise SystemExit(130) from None


def _main(args: argparse.Namespace) -> None:
    sets = parse_sets(args.sets)
    source = checkpoint_source(args.checkpoint, args) if args.checkpoint is not None else None
    config = source.config if source is not None else config_from_args(args)
    if args.dump_config:
        print(to_toml(config), end="")
        return
    source = source if source is not None else live_source(config)
    check_weights(config, source.weights)
    policies = ["greedy", *(["random"] if args.random_baseline else []), *(["privileged"] if args.privileged else [])]
    started = time.monotonic()
    episodes, summaries = evaluate(config, source.weights, policies, sets)
    wall_s = time.monotonic() - started
    out_dir = args.out if args.out is not None else source.run_dir / OUTPUT_DIR
    evaluation = config.evaluation
    workers = min(evaluation.workers, len(episodes))
    facts = {**source.facts,
             "protocol": f"{evaluation.episodes_per_start} episodes from each start of {', '.join(sets)}, "
                         f"capped at {evaluation.max_steps} steps; greedy = argmax Q",
             "seed": str(evaluation.seed),
             "intervals": f"{100 * evaluation.confidence:g}% percentile intervals of {evaluation.bootstrap_replicates} "
                          "bootstrap replicates (trials resampled within each start)",
             "processes": f"{workers} worker(s) x {evaluation.envs_per_worker} lockstep env(s), "
                          f"{torch_threads_per_worker(workers)} torch thread(s) each",
             "wall time": f"{wall_s:.1f} s",
             "date": datetime.datetime.now().isoformat(timespec="seconds")}
    paths = write_report(out_dir, episodes, summaries, evaluation.reward_bins, facts, evaluation.episodes_per_start,
                         to_toml(config), evaluation.confidence)
    print((out_dir / SUMMARY_MD).read_text())
    print("wrote " + ", ".join(str(path) for path in paths), file=sys.stderr)


if __name__ == "__main__":
    main()
