"""The grid runner: trains a grid of cells (strategy x replay capacity x learner option set) x seeds on the
protocol of deploy/grid/grid_cells.py, each run read on its greedy test curve, then reports.

Each run goes through the real distributed stack (deploy/launcher/stack.py, a subprocess) in
<runs-dir>/<run name>/ with the soak sampled beside it (deploy/labs/soak.py), then `evaluate --curve` (its greedy
test curve), the choice of its policy on the train starts among its last five kept, and `evaluate
--checkpoint` of that policy on both start sets. Each finished run is exported (deploy/studies/run_results.py) to
--export, small enough to commit; the report (deploy/studies/grid_report.py) reads exported runs only, so runs from
several machines merge (--merge) and it rebuilds from a fresh clone.

One run's steps and commands are deploy/grid/grid_job.py. `--cells` lists the grid's runs, numbered from 0; `--cell I` runs only the I-th, so a scheduler (a Slurm
array, a Kubernetes indexed job) can spread a grid over machines. Running the same command again resumes
every run from what its folder holds.

    .venv/bin/python deploy/grid/experiments.py --buffers 1000 --seeds 0,1,2          # the comparison's 21 runs
    .venv/bin/python deploy/grid/experiments.py --buffers 1000 --seeds 0,1,2 --cells  # its numbered runs
    .venv/bin/python deploy/grid/experiments.py --buffers 1000 --seeds 0,1,2 --cell 7 # one of them
    .venv/bin/python deploy/grid/experiments.py --strategies bmc --buffers 1000 --options nstep3,batch20 --seeds 0,1

Every other flag is a config flag passed to every run's stack and evaluation (--preset, default drive;
--config FILE, --env.max_steps 500, ...; see deploy/launcher/stack.py --help).
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

from common.eta import clock_time
from common.exploration.names import STRATEGIES
from common.presets import GRID_UPDATES
from common.shell import on_stop_signals
from deploy.grid.grid_cells import (DONE, FINAL_TRIALS, OPTION_SETS, PROTOCOL_PRESET, ExperimentError, RunSpec, counted,
                                       grid, next_step)
from deploy.grid.grid_job import POLL_S, RESULTS_DIR, Options, RunJob, check_config_flags, run_budget
from deploy.grid.run_progress import trained_share
from deploy.studies.run_results import ExportError


# --- the grid ----------------------------------------------------------------------------------------------------------

class GridStatus:
    """Runs done of all, the share of their budgets trained, and an ETA by runs: the running runs' own ETAs
    (their stacks'), then the runs still waiting, `parallel` at a time, each taking as long as the runs
    this session finished took or, before one has finished, as long as the running ones look to take."""

    def __init__(self, jobs: list[RunJob], parallel: int = 1) -> None:
        self.jobs = jobs
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

    def line(self) -> str:
        trained = sum(job.trained() for job in self.jobs)
        remaining = self.remaining_s()
        done = sum(job.finished and job.error is None for job in self.jobs)
        failed = sum(job.finished and job.error is not None for job in self.jobs)
        return (f"grid: {done}/{counted(len(self.jobs), 'run')} done" + (f", {failed} failed" if failed else "")
                + f", {100 * trained / max(len(self.jobs), 1):.1f}% of the budgets trained, "
                  f"elapsed {clock_time(time.monotonic() - self.started)}, "
                  f"ETA {'?' if remaining is None else clock_time(remaining)}")


def run_grid(specs: list[RunSpec], options: Options, parallel: int, numbers: list[int] | None = None,
             total: int | None = None) -> int:
    """Runs every spec (numbered in a grid of `total` runs: --cell runs one); returns the number of runs that
    failed (an interruption raises KeyboardInterrupt)."""
    stopping = threading.Event()
    numbers = numbers or list(range(len(specs)))
    jobs = [RunJob(number, total or len(specs), spec, options, stopping,
                   trained_at_start=trained_share(options.steps_dir(spec), run_budget(spec, options)))
            for number, spec in zip(numbers, specs)]
    # runs their folders already hold whole go first: they finish at once, so the counts say so from the start
    pending = deque(sorted(jobs, key=lambda job: step_of(options.steps_dir(job.spec),
                                                         run_budget(job.spec, options)) != DONE))
    active = []
    failed = 0
    status = GridStatus(jobs, parallel)
    last_shown = time.monotonic()

    def interrupt(*_) -> None:
        stopping.set()
        for job in active:
            job.interrupt()

    previous = on_stop_signals(interrupt)
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
                print(status.line(), flush=True)
            for job in [job for job in active if job.finished]:
                active.remove(job)
                failed += job.error is not None
                took = clock_time(time.monotonic() - job.started)
                outcome = f"FAILED after {took}: {job.error}" if job.error else f"{job.phase} in {took}"
                print(f"{job.tag}: {outcome}" + (f" | {job.headline}" if job.headline else ""), flush=True)
                print(status.line(), flush=True)
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    if stopping.is_set():
        raise KeyboardInterrupt
    return failed


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
    parser = argparse.ArgumentParser(prog="deploy/grid/experiments.py", description=__doc__, allow_abbrev=False,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--strategies", default=",".join(STRATEGIES),
                        help="comma-separated exploration strategies of the grid (default: all seven)")
    parser.add_argument("--buffers", default="1000", help="replay capacities in episodes (default: 1000)")
    parser.add_argument("--options", default="paper",
                        help="comma-separated learner option sets: " + ", ".join(
                            f"{name} ({doc})" for name, (doc, _) in OPTION_SETS.items()) + " (default: paper)")
    parser.add_argument("--seeds", default="0,1,2", help="run.seed of each run (default: 0,1,2)")
    parser.add_argument("--updates", type=int, default=GRID_UPDATES,
                        help=f"the budget of every run in learner updates (default: {GRID_UPDATES:,d})")
    parser.add_argument("--trials", type=int, default=FINAL_TRIALS,
                        help="trials per start of the chosen policy's evaluation on both start sets "
                             f"(default: {FINAL_TRIALS}; the paper's 30 where time allows)")
    parser.add_argument("--cells", action="store_true", help="list the grid's runs, numbered, with the step each "
                                                             "needs next, and exit")
    parser.add_argument("--cell", type=int, default=None, metavar="I",
                        help="run only the I-th run of --cells (from 0), e.g. $SLURM_ARRAY_TASK_ID")
    parser.add_argument("--parallel", type=int, default=1, help="runs at once (default: 1)")
    parser.add_argument("--curve-beside", action="store_true",
                        help="follow each run's test curve while it trains (one worker at nice 15, the learner on "
                             "the other cores); for machines with cores to spare. Default: the curve after "
                             "training, with every core")
    parser.add_argument("--runs-dir", type=Path, default=Path("runs/grid"),
                        help="where the run folders and results/ go (default: runs/grid)")
    parser.add_argument("--actors", type=int, default=None, help="actors per stack (default: the stack's)")
    parser.add_argument("--progress-s", type=float, default=60.0,
                        help="seconds between the status lines of the running runs and the grid (default: 60)")
    parser.add_argument("--report-only", action="store_true",
                        help="train and evaluate nothing; rebuild the report from the exported runs and say which "
                             "runs of the grid none of them holds finished")
    parser.add_argument("--export", type=Path, default=None,
                        help="where each finished run's small outputs go, to commit or copy (default: "
                             "<runs-dir>/results/runs); the report reads them from there")
    parser.add_argument("--merge", type=Path, action="append", default=[],
                        help="another folder of exported runs for the report, such as another machine's "
                             "(repeatable; a run already exported here wins)")
    return parser


def thread_flags(extra: list[str], parallel: int, curve_beside: bool, cores: int) -> list[str]:
    """The learner's torch threads unless the flags set them: its share of the cores with several runs at
    once, one core fewer with the curve followed beside it. A multi-threaded learner whose threads share a
    core with an evaluation stalls (8.8 to 0.3-1.0 updates/s), whatever the evaluation's niceness."""
    if any(flag.split("=")[0] == "--learner.torch_threads" for flag in extra):
        return []
    threads = cores // parallel - (1 if curve_beside else 0)
    return [] if parallel == 1 and not curve_beside else ["--learner.torch_threads", str(max(1, threads))]


def preset_flags(extra: list[str]) -> list[str]:
    """The protocol's preset unless the flags name one."""
    return [] if any(flag.split("=")[0] == "--preset" for flag in extra) else ["--preset", PROTOCOL_PRESET]


@dataclass(frozen=True)
class Plan:
    specs: list[RunSpec]
    numbers: list[int]
    options: Options
    parallel: int
    report_only: bool
    list_cells: bool
    grid_size: int


def parse_arguments(argv: list[str] | None) -> Plan:
    args, extra = build_parser().parse_known_args(argv)
    strategies = parse_list(args.strategies, str, "strategies")
    unknown = [name for name in strategies if name not in STRATEGIES]
    unknown_sets = [name for name in parse_list(args.options, str, "options") if name not in OPTION_SETS]
    if unknown or unknown_sets:
        raise ExperimentError(f"unknown {', '.join(unknown + unknown_sets)}; strategies: {', '.join(STRATEGIES)}; "
                              f"option sets: {', '.join(OPTION_SETS)}")
    for name in ("updates", "parallel", "trials", "actors", "progress_s"):
        value = getattr(args, name)
        if value is not None and value <= 0:
            raise ExperimentError(f"--{name.replace('_', '-')}: must be > 0, got {value}")
    specs = grid(strategies, parse_list(args.buffers, int, "buffers"), parse_list(args.seeds, int, "seeds"),
                 parse_list(args.options, str, "options"))
    numbers, grid_size = list(range(len(specs))), len(specs)
    if args.cell is not None:
        if not 0 <= args.cell < len(specs):
            raise ExperimentError(f"--cell {args.cell}: the grid has runs 0 to {len(specs) - 1} (--cells lists them)")
        specs, numbers = [specs[args.cell]], [args.cell]
    extra = [*preset_flags(extra), *extra,
             *thread_flags(extra, args.parallel, args.curve_beside, os.cpu_count() or 1)]
    options = Options(args.runs_dir, args.updates, args.trials, args.actors, tuple(extra), args.progress_s,
                      args.export, tuple(args.merge), args.curve_beside)
    check_config_flags(specs, options)
    return Plan(specs, numbers, options, args.parallel, args.report_only, args.cells, grid_size)


def step_of(run_dir: Path, budget: int) -> str:
    """The run's next step, or what keeps it from being read (a damaged checkpoint or config): that run
    fails with the reason when its turn comes, and the others go on."""
    try:
        return next_step(run_dir, budget)
    except ExperimentError as error:
        return f"unreadable ({error})"


def list_cells(plan: Plan) -> None:
    for number, spec in zip(plan.numbers, plan.specs):
        exported = plan.options.exported(spec)
        step = f"{DONE} (exported to {exported})" if exported else step_of(plan.options.run_dir(spec),
                                                                            run_budget(spec, plan.options))
        print(f"{number:3d}  {spec.name:32s} {spec.strategy:14s} buffer {spec.capacity:5d}  options {spec.options:15s} "
              f"seed {spec.seed}  next: {step}")


def missing_runs(plan: Plan) -> list[str]:
    """The runs that no folder of exported runs holds finished at this budget, each with the step its run
    folder needs next: the report after a scheduler's tasks says which of them did not finish."""
    folders = [plan.options.export_dir, *plan.options.merge]
    return [f"cell {number} {spec.name} (next: {step_of(plan.options.run_dir(spec), run_budget(spec, plan.options))})"
            for number, spec in zip(plan.numbers, plan.specs)
            if not any(plan.options.finished_export(spec, folder) for folder in folders)]


def main(argv: list[str] | None = None) -> int:
    try:
        plan = parse_arguments(argv)
        if plan.list_cells:
            list_cells(plan)
            return 0
    except ExperimentError as error:
        print(f"deploy/grid/experiments.py: error: {error}", file=sys.stderr)
        return 2
    started, options = time.monotonic(), plan.options
    print(f"grid: {counted(len(plan.specs), 'run')} under {options.runs_dir}/, {options.updates:,d} updates each, "
          f"{plan.parallel} at a time; flags: {' '.join(options.extra)}", flush=True)
    failed = 0
    if not plan.report_only:
        try:
            failed = run_grid(plan.specs, options, plan.parallel, plan.numbers, plan.grid_size)
        except KeyboardInterrupt:
            print("interrupted: the running stacks checkpointed; the same command resumes", file=sys.stderr)
            return 130
    elif missing := missing_runs(plan):
        print(f"grid: {counted(len(missing), 'run')} of {len(plan.specs)} not finished and exported: "
              + "; ".join(missing), flush=True)
    if not options.export_dir.is_dir():
        print(f"grid: no run has finished yet ({options.export_dir} is empty); no report", flush=True)
        return 1 if failed else 0
    from deploy.studies.grid_report import report_on  # the report's figures import matplotlib: not before a run
    try:
        paths = report_on([options.export_dir, *options.merge], options.runs_dir / RESULTS_DIR)
    except (ValueError, ExportError) as error:
        print(f"deploy/grid/experiments.py: cannot write the report: {error}", file=sys.stderr)
        return 1
    print(f"grid finished in {clock_time(time.monotonic() - started)}; {failed} failed; report: "
          + ", ".join(str(path) for path in paths), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
