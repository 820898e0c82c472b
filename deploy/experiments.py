"""The paper's comparison: train and evaluate a grid of strategies x replay capacities x seeds, then tabulate.

Each run of the grid goes through the real distributed stack (deploy/stack.py, a
subprocess) in the run folder <runs-dir>/<strategy>-b<capacity>-s<seed>/
(common/run_dir.py), then through `evaluate` (its greedy policy and the random
baseline, train and test starts, into the run's evaluation folder). Runs go one
after the other, or --parallel K at once (each learner then takes its share of
the cores, learner.torch_threads, unless the flags set it). A line per period
shows each running run (from the stack's status file, or evaluate's status
line) and the grid:
runs done of all, and an ETA from the env steps trained so far in this session.
Each run, once evaluated, is exported (deploy/run_results.py) to --export,
<runs-dir>/results/runs/ unless told: its evaluation, config, run summary and
training curves, small enough to commit. At the end, <runs-dir>/results/
receives the report on the exported runs and those of any --merge folder
(deploy/report.py, which also rebuilds it from committed runs alone): the
tables of the paper's tables 3-6 with bootstrap confidence intervals over the
seeds (results.md, results.csv: pooled rows and one row per seed, with every
run's updates), the figures of common/analysis/figures.py and the performance
profiles of deploy/performance_profile.py.

Every run keeps its policy now and then for a greedy learning curve
(learner.keep_every: the config's, or about GRID_KEPT_POLICIES over the budget
when it keeps none); `evaluate --curve <run folder>` draws it, after the run or
beside it (docs/evaluation-curves.md).

Stopping and running the same command again resumes: a run with an evaluation
and a checkpoint at the step budget is done; a run whose checkpoint is short of
the budget is resumed (--resume) and evaluated again; a trained run without an
evaluation is only evaluated; a run without a checkpoint starts over.

    .venv/bin/python deploy/experiments.py --strategies bmc,softmax --buffers 1000 --steps 40000 \\
        --trials 10 --preset local

Every other flag is a config flag passed to every run's stack and evaluation
(--preset, --config FILE, --env.max_steps 500, ...; see deploy/stack.py --help).
"""

from __future__ import annotations

import argparse
import csv
import datetime
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from actor.evaluation.status import is_evaluation_line
from common.analysis.intervals import Bootstrap, bootstrap_of
from common.analysis.tables import SUMMARY_CSV
from common.checkpoint import Checkpoint, CheckpointError
from common.config_cli import add_config_arguments, config_from_args, parse_flags
from common.eta import clock_time
from common.exploration.names import STRATEGIES
from common.options import ConfigError
from common.run_dir import RunDir, RunStatus, StatusError
from deploy.report import write_report
from deploy.run_results import collect, export_run, run_name

STACK_SCRIPT = Path(__file__).resolve().parent / "stack.py"
RESULTS_DIR = "results"
EXPORTED_RUNS = "runs"
# Keys the grid sets for each run; giving them as config flags would contradict it.
GRID_KEYS = {"run.name": "the run names", "run.seed": "--seeds", "run.runs_dir": "--runs-dir",
             "exploration.strategy": "--strategies", "replay.capacity": "--buffers",
             "learner.total_env_steps": "--steps", "evaluation.episodes_per_start": "--trials"}
POLL_S = 0.5
GRID_KEPT_POLICIES = 20  # policies a run keeps for its greedy curve when the runs' config keeps none
TRAIN, RESUME, EVALUATE, DONE = "train", "resume", "evaluate", "done"


class ExperimentError(RuntimeError):
    """A run or the grid cannot go on; the message says which and why."""


@dataclass(frozen=True)
class RunSpec:
    strategy: str
    capacity: int  # replay.capacity, episodes
    seed: int

    @property
    def name(self) -> str:
        return run_name(self.strategy, self.capacity, self.seed)


@dataclass(frozen=True)
class Options:
    runs_dir: Path
    steps: int  # learner.total_env_steps of every run
    trials: int | None  # evaluation.episodes_per_start; None keeps the config's
    actors: int | None
    extra: tuple[str, ...]  # config flags for every stack and evaluation
    progress_s: float
    export: Path | None = None  # where finished runs go (deploy/run_results.py); None: <runs-dir>/results/runs
    merge: tuple[Path, ...] = ()  # more folders of exported runs for the report (another machine's)

    def run_dir(self, spec: RunSpec) -> Path:
        return self.runs_dir / spec.name

    @property
    def export_dir(self) -> Path:
        return self.export if self.export is not None else self.runs_dir / RESULTS_DIR / EXPORTED_RUNS

    def run(self, spec: RunSpec) -> RunDir:
        return RunDir(self.run_dir(spec))


def grid(strategies: list[str], capacities: list[int], seeds: list[int]) -> list[RunSpec]:
    """Capacity, then seed, then strategy: the runs of one table come before those of the next."""
    return [RunSpec(strategy, capacity, seed) for capacity in capacities for seed in seeds for strategy in strategies]


# --- what a run still needs -----------------------------------------------------------------------------------

def checkpoint_env_steps(path: Path) -> int:
    """The learner's clock in a checkpoint: the env steps of the whole system when it was saved."""
    try:
        env_steps = Checkpoint.load(path).env_steps
    except CheckpointError as error:
        raise ExperimentError(f"cannot read the step count of {path}: {error}") from None
    if env_steps is None:
        raise ExperimentError(f"cannot read the step count of {path}: its clock has none")
    return env_steps


def next_step(run_dir: Path, budget: int) -> str:
    """TRAIN, RESUME, EVALUATE or DONE for the run in run_dir, from what it holds on disk."""
    run = RunDir(run_dir)
    evaluated = (run.evaluation / SUMMARY_CSV).is_file()
    if not run.checkpoint.is_file():
        return DONE if evaluated else TRAIN
    if checkpoint_env_steps(run.checkpoint) < budget:
        return RESUME  # also a run evaluated earlier with a smaller budget
    return DONE if evaluated else EVALUATE


def trained_env_steps(run_dir: Path, budget: int) -> int:
    """How much of the budget a run has trained: all of it once it is done, else what its checkpoint
    holds (0 without a readable one)."""
    try:
        step = next_step(run_dir, budget)
        if step in (TRAIN, DONE):
            return budget if step == DONE else 0
        return min(checkpoint_env_steps(RunDir(run_dir).checkpoint), budget)
    except ExperimentError:
        return 0


def set_aside_stale_files(run_dir: Path) -> Path | None:
    """Moves the logs of an attempt that never checkpointed out of the way of a fresh start.

    Otherwise the new recorder would write traffic-2.mcap next to the old file and the
    figures would read both as one run.
    """
    run = RunDir(run_dir)
    stale = run.wire_log_segments() + [path for path in [run.logs] if path.is_dir()]
    if not stale:
        return None
    target = run.abandoned(datetime.datetime.now().strftime("%Y%m%d-%H%M%S"))
    target.mkdir(parents=True)
    for path in stale:
        shutil.move(path, target / path.name)
    return target


# --- the commands of one run ------------------------------------------------------------------------------

def stack_command(spec: RunSpec, options: Options, resume: bool) -> list[str]:
    command = [sys.executable, str(STACK_SCRIPT), *options.extra, *grid_flags(spec, options)]
    command += ["--actors", str(options.actors)] if options.actors else []
    return command + (["--resume"] if resume else [])


def evaluate_command(spec: RunSpec, options: Options, privileged: bool = False) -> list[str]:
    """evaluate's command for a run: its greedy policy and the random baseline, and with `privileged` the
    map-reading driver too (the grid's first run: the baselines need no training, so once is enough)."""
    run = options.run(spec)
    command = [sys.executable, "-m", "actor.evaluate", "--checkpoint", str(run.root),
               "--out", str(run.evaluation), *(["--privileged"] if privileged else []), *options.extra]
    return command + (["--evaluation.episodes_per_start", str(options.trials)] if options.trials else [])


def grid_flags(spec: RunSpec, options: Options) -> list[str]:
    return ["--run.name", spec.name, "--run.runs_dir", str(options.runs_dir), "--run.seed", str(spec.seed),
            "--exploration.strategy", spec.strategy, "--replay.capacity", str(spec.capacity),
            "--learner.total_env_steps", str(options.steps)]


def check_config_flags(specs: list[RunSpec], options: Options) -> None:
    """Builds every run's config as the stack will, so a bad flag fails here and not after an hour."""
    for token in options.extra:
        key = token.removeprefix("--").split("=")[0]
        if key in GRID_KEYS:
            raise ExperimentError(f"--{key} is set by the grid for each run ({GRID_KEYS[key]}); do not pass it")
    parser = config_parser()
    for spec in specs:
        try:
            config_from_args(parse_flags(parser, [*options.extra, *grid_flags(spec, options)]))
        except ConfigError as error:
            raise ExperimentError(f"config error: {error}") from None


def config_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="deploy/experiments.py", add_help=False,
                                     usage="deploy/experiments.py [options] [config flags of deploy/stack.py --help]")
    add_config_arguments(parser)
    return parser


def report_bootstrap(options: Options) -> Bootstrap:
    """The intervals' settings (evaluation.bootstrap_replicates, .confidence, .seed) of the runs' config flags."""
    return bootstrap_of(config_from_args(parse_flags(config_parser(), list(options.extra))))


# --- child processes -------------------------------------------------------------------------------------------

class Child:
    """A subprocess whose output goes to a log file; keeps its latest status line (those `is_status`
    accepts) and echoes the others.

    It runs in a session of its own, so a Ctrl-C in the terminal reaches it once, forwarded by the runner.
    """

    def __init__(self, command: list[str], log_path: Path, is_status: Callable[[str], bool] | None,
                 echo_prefix: str | None) -> None:
        log_path.parent.mkdir(parents=True, exist_ok=True)
        self.is_status = is_status
        self.echo_prefix = echo_prefix  # None: other lines stay in the log
        self.latest = ""
        self.tail: deque[str] = deque(maxlen=8)  # for the error message when it fails
        self._log = open(log_path, "ab")
        self.process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                        stdin=subprocess.DEVNULL, start_new_session=True)
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        pending = ""
        while chunk := self.process.stdout.read1(65536):
            self._log.write(chunk)
            self._log.flush()
            *lines, pending = re.split(r"[\r\n]", pending + chunk.decode(errors="replace"))
            for line in filter(None, (line.strip() for line in lines)):
                self._take(line)
        if pending.strip():
            self._take(pending.strip())

    def _take(self, line: str) -> None:
        if self.is_status is not None and self.is_status(line):
            self.latest = line
            return
        self.tail.append(line)
        if self.echo_prefix is not None:
            print(f"{self.echo_prefix}: {line}", flush=True)

    def interrupt(self) -> None:
        """SIGINT, once: the stack stops its processes (the learner checkpoints), evaluate stops its workers."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)

    def wait(self) -> int:
        code = self.process.wait()
        self._reader.join()
        self._log.close()
        return code


# --- one run --------------------------------------------------------------------------------------------------------

@dataclass
class RunJob:
    """One run of the grid, stepped through TRAIN/RESUME then EVALUATE on its own thread."""

    number: int
    total: int
    spec: RunSpec
    options: Options
    stopping: threading.Event
    phase: str = "waiting"
    child: Child | None = None
    error: str | None = None
    headline: str = ""
    trained_at_start: int = 0  # env steps of its checkpoint when the grid started
    took_s: float | None = None  # wall time of its training and evaluation, once it ran them in this session
    started: float = field(default_factory=time.monotonic)
    started_at: float = field(default_factory=time.time)  # wall clock, to tell this stack's status from older ones
    thread: threading.Thread | None = None

    def start(self) -> None:
        self.started, self.started_at = time.monotonic(), time.time()
        self.thread = threading.Thread(target=self._run, name=self.spec.name, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            self._steps()
        except ExperimentError as error:
            self.error = str(error)
        except Exception as error:  # the thread's end: whatever went wrong must reach the grid's report
            self.error = f"{type(error).__name__}: {error}"
        self.child = None

    def _steps(self) -> None:
        run_dir, run = self.options.run_dir(self.spec), self.options.run(self.spec)
        step = next_step(run_dir, self.options.steps)
        summary = run.evaluation / SUMMARY_CSV
        if step == DONE:
            self.phase, self.headline = "already done", evaluation_headline(summary)
            return
        print(f"{self.tag}: {step}", flush=True)
        if step == TRAIN:
            moved = set_aside_stale_files(run_dir)
            if moved is not None:
                print(f"{self.tag}: an earlier attempt left no checkpoint; its logs moved to {moved}", flush=True)
        if step in (TRAIN, RESUME):
            self.phase = "resuming" if step == RESUME else "training"
            self._child(stack_command(self.spec, self.options, resume=step == RESUME), run.log("stack"),
                        None, "the stack", echo=True)  # its figures are in the status file
            reached = checkpoint_env_steps(run.checkpoint)
            if reached < self.options.steps:
                raise ExperimentError(f"the stack stopped at {reached:,d} of {self.options.steps:,d} env steps")
        self.phase = "evaluating"
        self._child(evaluate_command(self.spec, self.options, privileged=self.number == 1), run.log("evaluate"),
                    is_evaluation_line, "evaluate", echo=False)  # its summary.md, printed at the end, is in the log
        self.phase, self.headline = "done", evaluation_headline(summary)
        self.took_s = time.monotonic() - self.started
        folder = export_run(run, self.options.export_dir)
        print(f"{self.tag}: exported to {folder}", flush=True)

    def _child(self, command: list[str], log_path: Path, is_status: Callable[[str], bool] | None, what: str,
               echo: bool) -> None:
        if self.stopping.is_set():
            raise ExperimentError("interrupted")
        self.child = Child(command, log_path, is_status, self.tag if echo else None)
        if self.stopping.is_set():  # the interruption came while the child was starting
            self.child.interrupt()
        code = self.child.wait()
        if self.stopping.is_set():
            raise ExperimentError("interrupted")
        if code != 0:
            tail = "\n    ".join(self.child.tail)
            raise ExperimentError(f"{what} exited with code {code} (log: {log_path}); its last lines:\n    {tail}")

    def status(self) -> RunStatus | None:
        """The status file of this job's stack; None before it wrote one (an older one does not count)."""
        try:
            status = RunStatus.read(self.options.run(self.spec).status)
        except StatusError:
            return None
        return status if status.time >= self.started_at else None

    def latest_line(self) -> str:
        """The stack's figures while training, evaluate's status line while evaluating."""
        if self.phase in ("training", "resuming"):
            status = self.status()
            return stack_line(status) if status is not None else ""
        return self.child.latest if self.child is not None else ""

    def remaining_s(self) -> float | None:
        """Its stack's ETA while it trains (None if unknown yet), nothing more once it evaluates."""
        if self.phase in ("training", "resuming"):
            status = self.status()
            return None if status is None else status.eta_s
        return 0.0

    def trained(self) -> int:
        """Env steps of the budget trained so far."""
        budget = self.options.steps
        if self.phase in ("evaluating", "done", "already done"):
            return budget
        status = self.status() if self.phase in ("training", "resuming") else None
        return self.trained_at_start if status is None else max(self.trained_at_start, min(status.env_steps, budget))

    @property
    def tag(self) -> str:
        return f"[{self.number}/{self.total}] {self.spec.name}"

    @property
    def finished(self) -> bool:
        return self.thread is not None and not self.thread.is_alive()


def stack_line(status: RunStatus) -> str:
    """'env steps 12,000/60,000 (20.0%), updates 600, return(100) 3.21, restarts 0, ETA 40:00' of a stack."""
    budget = max(status.total_env_steps, 1)
    mean_return = "–" if status.mean_return is None else f"{status.mean_return:.2f}"
    eta = "?" if status.eta_s is None else clock_time(status.eta_s)
    return (f"env steps {status.env_steps:,d}/{status.total_env_steps:,d} ({100 * status.env_steps / budget:.1f}%), "
            f"updates {status.updates:,d}, return(100) {mean_return}, restarts {sum(status.restarts.values())}, "
            f"ETA {eta}")


def evaluation_headline(summary_csv: Path) -> str:
    """'test: mean length 812.4 [701.0, 905.2], CFR 35.0% [28.3, 41.7]' from the greedy rows of an evaluate
    summary.csv (the intervals over its trials, when the file has them)."""
    with summary_csv.open(newline="") as handle:
        rows = [row for row in csv.DictReader(handle) if row["policy"] == "greedy"]

    def interval(row: dict, statistic: str, scale: float) -> str:
        if not row.get(f"{statistic}_low"):
            return ""
        return f" [{scale * float(row[statistic + '_low']):,.1f}, {scale * float(row[statistic + '_high']):,.1f}]"

    return "; ".join(f"{row['start_set']}: mean length {float(row['mean_length']):,.1f}{interval(row, 'mean_length', 1)}, "
                     f"CFR {100 * float(row['cfr']):.1f}%{interval(row, 'cfr', 100)}" for row in rows)


# --- the grid ----------------------------------------------------------------------------------------------------------

class GridStatus:
    """Runs done of all, the share of env steps trained, and an ETA by runs: the running runs' own ETAs
    (their stacks'), then the runs still waiting, `parallel` at a time, each taking as long as the runs
    this session finished took or, before one has finished, as long as the running ones look to take."""

    def __init__(self, jobs: list[RunJob], budget: int, parallel: int = 1) -> None:
        self.jobs = jobs
        self.total = len(jobs) * budget
        self.parallel = parallel
        self.started = time.monotonic()

    def remaining_s(self) -> float | None:
        running = [job for job in self.jobs if job.thread is not None and not job.finished]
        waiting = sum(job.thread is None for job in self.jobs)
        left = [job.remaining_s() for job in running]
        if None in left:
            return None
        took = [job.took_s for job in self.jobs if job.took_s is not None]
        projected = [time.monotonic() - job.started + seconds for job, seconds in zip(running, left)]
        per_run = took or projected
        if waiting and not per_run:
            return None
        waves = -(-waiting // self.parallel)
        return max(left, default=0.0) + (waves * sum(per_run) / len(per_run) if waiting else 0.0)

    def _trained(self) -> int:
        return sum(job.trained() for job in self.jobs)

    def line(self) -> str:
        trained = self._trained()
        remaining = self.remaining_s()
        done = sum(job.finished and job.error is None for job in self.jobs)
        failed = sum(job.finished and job.error is not None for job in self.jobs)
        return (f"grid: {done}/{len(self.jobs)} runs done" + (f", {failed} failed" if failed else "")
                + f", {100 * trained / max(self.total, 1):.1f}% of the env steps trained, "
                  f"elapsed {clock_time(time.monotonic() - self.started)}, "
                  f"ETA {'?' if remaining is None else clock_time(remaining)}")


def run_grid(specs: list[RunSpec], options: Options, parallel: int) -> int:
    """Runs every spec; returns the number of runs that failed (an interruption raises KeyboardInterrupt)."""
    stopping = threading.Event()
    jobs = [RunJob(number, len(specs), spec, options, stopping,
                   trained_at_start=trained_env_steps(options.run_dir(spec), options.steps))
            for number, spec in enumerate(specs, 1)]
    pending, active = deque(jobs), []
    failed = 0
    grid = GridStatus(jobs, options.steps, parallel)
    last_shown = time.monotonic()

    def interrupt(*_) -> None:
        stopping.set()
        for job in active:
            if job.child is not None:
                job.child.interrupt()

    previous = {signum: signal.signal(signum, interrupt) for signum in (signal.SIGINT, signal.SIGTERM)}
    try:
        while pending or active:
            while pending and len(active) < parallel and not stopping.is_set():
                job = pending.popleft()
                job.start()
                active.append(job)
            if stopping.is_set():
                pending.clear()
            time.sleep(POLL_S)
            if time.monotonic() - last_shown >= options.progress_s:
                last_shown = time.monotonic()
                for job in active:
                    if line := job.latest_line():
                        print(f"{job.tag} {job.phase} {clock_time(time.monotonic() - job.started)} | {line}",
                              flush=True)
                print(grid.line(), flush=True)
            for job in [job for job in active if job.finished]:
                active.remove(job)
                failed += job.error is not None
                took = clock_time(time.monotonic() - job.started)
                outcome = f"FAILED after {took}: {job.error}" if job.error else f"{job.phase} in {took}"
                print(f"{job.tag}: {outcome}" + (f" | {job.headline}" if job.headline else ""), flush=True)
                print(grid.line(), flush=True)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    if stopping.is_set():
        raise KeyboardInterrupt
    return failed


# --- the results ------------------------------------------------------------------------------------------------------

def write_results(specs: list[RunSpec], options: Options, facts: dict[str, str]) -> list[Path]:
    """Exports every evaluated run of the grid, then reports on the exported runs (with those of --merge);
    returns the files written."""
    for spec in specs:
        if (options.run(spec).evaluation / SUMMARY_CSV).is_file():
            export_run(options.run(spec), options.export_dir)
    def warn(line: str) -> None:
        print(line, file=sys.stderr)

    runs = collect([options.export_dir, *options.merge], warn=warn)
    return write_report(runs, options.runs_dir / RESULTS_DIR, facts, report_bootstrap(options), warn)


# --- command line ----------------------------------------------------------------------------------------------------

def parse_list(text: str, kind, what: str) -> list:
    try:
        values = [kind(part.strip()) for part in text.split(",") if part.strip()]
    except ValueError:
        raise ExperimentError(f"--{what}: expected a comma-separated list, got {text!r}") from None
    if not values or len(set(values)) != len(values):
        raise ExperimentError(f"--{what}: expected distinct values, got {text!r}")
    return values


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="deploy/experiments.py", description=__doc__, allow_abbrev=False,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--strategies", default=",".join(STRATEGIES), help="comma-separated (default: all seven)")
    parser.add_argument("--buffers", default="1000,2000", help="replay capacities in episodes (default: 1000,2000)")
    parser.add_argument("--seeds", default="0", help="run.seed of each run (default: 0)")
    parser.add_argument("--steps", type=int, required=True, help="learner.total_env_steps of every run")
    parser.add_argument("--trials", type=int, default=None,
                        help="evaluation.episodes_per_start (default: the config's, 30 in the paper preset)")
    parser.add_argument("--parallel", type=int, default=1, help="runs at once (default: 1)")
    parser.add_argument("--runs-dir", type=Path, default=Path("runs/experiments"),
                        help="where the runs and results/ go (default: runs/experiments)")
    parser.add_argument("--actors", type=int, default=None, help="actors per stack (default: the stack's)")
    parser.add_argument("--progress-s", type=float, default=30.0,
                        help="seconds between the status lines of the running runs and the grid (default: 30)")
    parser.add_argument("--report-only", action="store_true",
                        help="train and evaluate nothing; export the evaluated runs on disk and rebuild results/")
    parser.add_argument("--export", type=Path, default=None,
                        help="where each finished run's small outputs go, to commit or copy (default: "
                             "<runs-dir>/results/runs); the report reads them from there")
    parser.add_argument("--merge", type=Path, action="append", default=[],
                        help="another folder of exported runs for the report, such as another machine's "
                             "(repeatable; a run already exported here wins)")
    return parser


def learner_threads_flags(extra: list[str], parallel: int, cores: int) -> list[str]:
    """With several runs at once, each learner gets its share of the cores unless the flags say otherwise:
    learners of torch's default (all cores each) oversubscribe the CPU, which slows an update several times."""
    if parallel == 1 or any(flag.split("=")[0] == "--learner.torch_threads" for flag in extra):
        return []
    return ["--learner.torch_threads", str(max(1, cores // parallel))]


def keep_flags(extra: list[str], steps: int) -> list[str]:
    """Every run keeps policies for its greedy learning curve (`evaluate --curve`): when the flags' config
    keeps none (the paper preset), about GRID_KEPT_POLICIES over the budget."""
    try:
        learner = config_from_args(parse_flags(config_parser(), extra)).learner
    except ConfigError:
        return []  # check_config_flags says what is wrong
    if learner.keep_every or learner.keep_every_s:
        return []
    return ["--learner.keep_every", str(max(1, round(steps / learner.env_steps_per_update / GRID_KEPT_POLICIES)))]


def parse_arguments(argv: list[str] | None) -> tuple[list[RunSpec], Options, int, bool]:
    args, extra = build_parser().parse_known_args(argv)
    unknown_strategies = [name for name in parse_list(args.strategies, str, "strategies") if name not in STRATEGIES]
    if unknown_strategies:
        raise ExperimentError(f"--strategies: unknown {', '.join(unknown_strategies)}; choose from {', '.join(STRATEGIES)}")
    for name in ("steps", "parallel", "trials", "actors", "progress_s"):
        value = getattr(args, name)
        if value is not None and value <= 0:
            raise ExperimentError(f"--{name.replace('_', '-')}: must be > 0, got {value}")
    specs = grid(parse_list(args.strategies, str, "strategies"), parse_list(args.buffers, int, "buffers"),
                 parse_list(args.seeds, int, "seeds"))
    extra = [*extra, *learner_threads_flags(extra, args.parallel, os.cpu_count() or 1), *keep_flags(extra, args.steps)]
    options = Options(args.runs_dir, args.steps, args.trials, args.actors, tuple(extra), args.progress_s,
                      args.export, tuple(args.merge))
    check_config_flags(specs, options)
    return specs, options, args.parallel, args.report_only


def main(argv: list[str] | None = None) -> int:
    try:
        specs, options, parallel, report_only = parse_arguments(argv)
    except ExperimentError as error:
        print(f"deploy/experiments.py: error: {error}", file=sys.stderr)
        return 2
    started = time.monotonic()
    plan = {spec: next_step(options.run_dir(spec), options.steps) for spec in specs}
    print(f"grid: {len(specs)} runs under {options.runs_dir}/, budget {options.steps:,d} env steps each, "
          f"{parallel} at a time; to do: " + ", ".join(f"{spec.name} {step}" for spec, step in plan.items()), flush=True)
    failed = 0
    if not report_only:
        try:
            failed = run_grid(specs, options, parallel)
        except KeyboardInterrupt:
            print("interrupted: the running stacks checkpointed; the same command resumes", file=sys.stderr)
            return 130
    facts = {"runs": ", ".join(spec.name for spec in specs), "budget": f"{options.steps:,d} env steps per run",
             "trials": f"{options.trials or 'the config’s'} per start", "config flags": " ".join(options.extra) or "none",
             "date": datetime.datetime.now().isoformat(timespec="seconds")}
    try:
        paths = write_results(specs, options, facts)
    except ValueError as error:  # ComparisonError, or data a figure cannot draw
        print(f"deploy/experiments.py: cannot write the results: {error}", file=sys.stderr)
        return 1
    print(f"grid finished in {clock_time(time.monotonic() - started)}; {failed} failed; results: "
          + ", ".join(str(path) for path in paths), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
