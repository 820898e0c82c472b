"""The main job (deploy/run.sh): the grid's BMC cell at buffer 1,000 (the drive preset) trained by the stack,
then read as the grid reads a run: its greedy test curve, its policy chosen on the train starts among its
last five kept, and that policy evaluated on both start sets. It ends with the chosen policy in
runs/<run>/policy.pt and its evaluation in runs/<run>/evaluation/.

Every flag of deploy/launcher/stack.py --help applies (the preset, the strategy, --resume, ...); with another preset
or budget the same steps follow. Stopped by Ctrl-C, SIGTERM or SIGHUP (but under nohup), it stops where it
is (the stack checkpoints); the same command with --resume (while training) or as it was (after) goes on.
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
from pathlib import Path
from typing import Callable

from actor.evaluation import EvaluationError
from common.config_cli import parse_config_or_exit
from common.run_dir import RunDir
from common.shell import env_stopping_with_this, on_stop_signals
from deploy.grid.experiments import preset_flags
from deploy.grid.grid_job import Options, choice_commands, curve_commands, evaluate_commands
from deploy.grid.grid_cells import (CHOOSE, CURVE, DONE, EVALUATE, FINAL_TRIALS, RESUME, TRAIN, ExperimentError, choose,
                               next_step, read_choice)
from deploy.studies.run_results import greedy_headline
from deploy.launcher.stack import build_parser

STACK_SCRIPT = Path(__file__).resolve().parent / "launcher" / "stack.py"
POLICY_FILE = "policy.pt"
KEEP_EVERY = 1_000  # updates between kept policies when the config keeps none
STOPPED = "main job: stopped; the same command (with --resume while it trains) goes on"


def stoppable(job: Callable[[], int]) -> int:
    """Runs the job with SIGTERM (a service manager's stop; as PID 1 of a container it would be ignored) and
    SIGHUP (a closed terminal) taken as Ctrl-C: what the job runs checkpoints, and it ends in one line, 130.
    SIGINT too, since a job started in the background of a script inherits it ignored, as the stack does not."""
    on_stop_signals(signal.default_int_handler)
    try:
        return job()
    except KeyboardInterrupt:
        print(STOPPED, file=sys.stderr, flush=True)
        return 130


def call(command: list[str]) -> None:
    child = subprocess.Popen(command, env=env_stopping_with_this())  # it stops if this dies
    try:
        code = child.wait()
    except KeyboardInterrupt:
        stop_child(child)
        raise
    if code != 0:
        raise SystemExit(code)


def stop_child(child: subprocess.Popen) -> None:
    """Hands the stop on (a terminal's Ctrl-C reached the child already; a signal to this process alone did
    not) and waits while the child checkpoints, so that nothing is left running behind the job."""
    while True:
        try:
            child.send_signal(signal.SIGINT)
            child.wait()
            return
        except KeyboardInterrupt:
            continue


def read_run(run: RunDir, options: Options, budget: int) -> None:
    """The steps after training, each as the grid takes it, until the run is done."""
    while (step := next_step(run.root, budget)) != DONE:
        print(f"main job: {step} ({run.root})", flush=True)
        if step == CURVE:
            for command in curve_commands(run, options):
                call(command)
        elif step == CHOOSE:
            for command in choice_commands(run, options):
                call(command)
            choice = choose(run)
            print(f"main job: chose the policy kept at {choice['updates']:,d} updates on the train starts "
                  f"(train CFR {100 * choice['train_cfr']:.0f}% at {choice['trials_per_start']} trials per start)")
        elif step == EVALUATE:
            for command in evaluate_commands(run, options):
                call(command)
        else:
            raise SystemExit(f"main job: the run stopped short of its budget; `deploy/run.sh --resume` with "
                             f"the same flags trains on ({run.root})")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    flags = [*preset_flags(argv), *argv]
    if any(flag in ("-h", "--help", "--dump-config") for flag in argv):
        call([sys.executable, str(STACK_SCRIPT), *flags])
        return 0
    _, config = parse_config_or_exit(build_parser(), flags)
    if not (config.learner.keep_every or config.learner.keep_every_s):  # the paper preset keeps none
        print(f"main job: keeping a policy every {KEEP_EVERY:,d} updates to choose among "
              f"(--learner.keep_every {KEEP_EVERY})", flush=True)
        flags += ["--learner.keep_every", str(KEEP_EVERY)]
        _, config = parse_config_or_exit(build_parser(), flags)
    run, budget = RunDir.of(config), config.pace.total_env_steps
    if next_step(run.root, budget) in (TRAIN, RESUME):
        call([sys.executable, str(STACK_SCRIPT), *flags])
    try:
        read_run(run, Options(Path(config.run.runs_dir), 0, FINAL_TRIALS, None, (), 0.0), budget)
    except (ExperimentError, EvaluationError) as error:
        print(f"main job: error: {error}", file=sys.stderr)
        return 1
    policy = run.root / POLICY_FILE
    shutil.copy2(run.policy(read_choice(run)["updates"]), policy)
    print(f"main job: done. The chosen policy: {policy} (kept at {read_choice(run)['updates']:,d} updates); "
          f"its evaluation: {run.evaluation}/summary.md\n  {greedy_headline(run.evaluation)}")
    return 0


if __name__ == "__main__":
    sys.exit(stoppable(main))
