"""Submits a grid of deploy/grid/experiments.py to Slurm (docs/slurm.md): an array of one task per run
(deploy/slurm/grid.sbatch, SLURM_ARRAY_TASK_ID its --cell) and, after every task has ended
(--dependency=afterany), the job that builds the report and says which runs are missing.

    .venv/bin/python deploy/slurm/submit.py --runs-dir /shared/grid --buffers 1000 --seeds 0,1,2
    .venv/bin/python deploy/slurm/submit.py --runs-dir /shared/grid --partition cpu --max-running 7 --dry-run

Every flag not listed below is a grid flag, given to every task and to the report alike. Each setting comes
from its flag, else its D3RQN_SLURM_* variable, else grid.sbatch's #SBATCH line (one run's measured needs).
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from deploy.grid import experiments
from deploy.grid.grid_cells import ExperimentError, counted

ROOT = Path(__file__).resolve().parents[2]
SCRIPT = Path(__file__).resolve().with_name("grid.sbatch")
SETTINGS = {"cpus": "cpus-per-task", "mem": "mem", "time": "time", "partition": "partition"}  # flag: sbatch's
REPORT_MEM = "2G"  # the report reads exports only; matplotlib and the bootstrap hold well under a GB
REPORT_TIME = "1:00:00"
SET_HERE = ("--cell", "--cells", "--parallel", "--report-only", "--runs-dir")  # the submission sets these


class SubmitError(RuntimeError):
    """The grid cannot be submitted; the message says why."""


def directives(script: Path = SCRIPT) -> dict[str, str]:
    """The script's #SBATCH --name=value lines: the defaults of a task's settings."""
    return dict(re.findall(r"^#SBATCH --([a-z-]+)=(\S+)", script.read_text(), re.M))


def settings(args: argparse.Namespace, environ=os.environ) -> dict[str, str]:
    """sbatch's option -> value for a task: its flag, else D3RQN_SLURM_<FLAG>, else the script's line."""
    defaults, chosen = directives(), {}
    for flag, option in SETTINGS.items():
        value = getattr(args, flag) or environ.get(f"D3RQN_SLURM_{flag.upper()}") or defaults.get(option)
        if value:
            chosen[option] = value
    return chosen


@dataclass(frozen=True)
class Submission:
    array: list[str]  # the sbatch command of the tasks
    report: list[str]  # that of the report, less its --dependency (the array's job id, known once submitted)
    runs: int
    logs: Path


def submission(args: argparse.Namespace, grid_flags: list[str], environ=os.environ) -> Submission:
    """The two sbatch commands of a grid, its flags checked as its runner will."""
    if given := [flag for flag in grid_flags if flag.split("=")[0] in SET_HERE]:
        raise SubmitError(f"{', '.join(given)}: set by the submission for each job; give --runs-dir to "
                          "submit.py itself")
    runs_dir = args.runs_dir.resolve()
    try:
        plan = experiments.parse_arguments([*grid_flags, "--runs-dir", str(runs_dir)])
    except ExperimentError as error:
        raise SubmitError(f"the grid's flags: {error}") from None
    if args.max_running is not None and args.max_running <= 0:
        raise SubmitError(f"--max-running: must be > 0, got {args.max_running}")
    chosen, logs = settings(args, environ), runs_dir / "slurm"
    common = ["sbatch", "--parsable", f"--chdir={ROOT}", f"--export=ALL,D3RQN_ROOT={ROOT}"]
    tasks = f"0-{plan.grid_size - 1}" + (f"%{args.max_running}" if args.max_running else "")
    array = [*common, f"--array={tasks}", f"--output={logs}/%x-%A_%a.out",
             *(f"--{option}={value}" for option, value in chosen.items())]
    report = [*common, "--job-name=d3rqn-grid-report", "--no-requeue", f"--output={logs}/%x-%j.out",
              f"--cpus-per-task={chosen['cpus-per-task']}", f"--mem={REPORT_MEM}", f"--time={REPORT_TIME}",
              *([f"--partition={chosen['partition']}"] if "partition" in chosen else [])]
    flags = [str(SCRIPT), *grid_flags, "--runs-dir", str(runs_dir)]
    return Submission([*array, *flags], [*report, *flags], plan.grid_size, logs)


def sbatch(command: list[str]) -> str:
    """Submits; the job's id."""
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    except FileNotFoundError:
        raise SubmitError("no sbatch here: submit from a machine of the cluster") from None
    if done.returncode != 0:
        raise SubmitError(f"sbatch refused the job ({done.returncode}): {done.stderr.strip()}")
    return done.stdout.strip().split(";")[0]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="deploy/slurm/submit.py", description=__doc__, allow_abbrev=False,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs-dir", type=Path, required=True,
                        help="the run folders, on storage every node mounts at the same path")
    parser.add_argument("--partition", help="the partition (default: $D3RQN_SLURM_PARTITION, else the cluster's)")
    parser.add_argument("--time", help="a task's time limit; a run still training then is requeued and goes on "
                                       "(default: $D3RQN_SLURM_TIME, else grid.sbatch's)")
    parser.add_argument("--mem", help="a task's memory (default: $D3RQN_SLURM_MEM, else grid.sbatch's)")
    parser.add_argument("--cpus", help="a task's CPUs (default: $D3RQN_SLURM_CPUS, else grid.sbatch's)")
    parser.add_argument("--max-running", type=int, default=None, help="tasks running at once (default: all)")
    parser.add_argument("--dry-run", action="store_true", help="print the sbatch commands and submit nothing")
    return parser


def main(argv: list[str] | None = None) -> int:
    args, grid_flags = build_parser().parse_known_args(argv)
    try:
        plan = submission(args, grid_flags)
        if args.dry_run:
            print(shlex.join(plan.array), shlex.join([*plan.report[:2], "--dependency=afterany:<array>",
                                                      *plan.report[2:]]), sep="\n")
            return 0
        plan.logs.mkdir(parents=True, exist_ok=True)  # sbatch writes no log into a folder that is not there
        array = sbatch(plan.array)
        report = sbatch([*plan.report[:2], f"--dependency=afterany:{array}", *plan.report[2:]])
    except SubmitError as error:
        print(f"deploy/slurm/submit.py: error: {error}", file=sys.stderr)
        return 2
    print(f"grid: {counted(plan.runs, 'run')} as array job {array}; the report as job {report} once they have "
          f"ended; logs in {plan.logs}/ (squeue -j {array},{report})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
