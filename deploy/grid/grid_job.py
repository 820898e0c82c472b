"""One run of a grid, step by step (deploy/grid/grid_cells.py decides the steps from its folder): its config and
commands (the stack, the greedy test curve, the choice, the final evaluation), and RunJob, which runs them
as children with the soak beside the stack. deploy/grid/experiments.py runs a grid of these.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from actor.evaluation.status import is_evaluation_line
from common.config import Config
from common.config_cli import add_config_arguments, config_from_args, parse_flags
from common.eta import clock_time
from common.schema.fields import ConfigError
from common.run_dir import RunDir, RunStatus, StatusError
from deploy.grid.child_process import Child
from deploy.labs.soak import TreePeak
from actor.evaluation.curve import LATE_FROM
from deploy.grid.grid_cells import (CHOOSE, CURVE, CURVE_DENSE_UNTIL, CURVE_LATE_EVERY, DONE, EVALUATE, RESUME, TRAIN,
                                       ExperimentError, RunSpec, budget_env_steps, checkpoint_env_steps,
                                       choice_candidates, choose, chosen_updates, curve_read, curve_wanted, keep_every,
                                       late_kinds, next_step, read_cell, read_choice, shadow_curve_done, shadow_kinds,
                                       to_evaluate, write_cell)
from deploy.grid.run_progress import set_aside_stale_files, trains_since
from deploy.grid.step_record import close_killed_step, open_step, record_step
from deploy.studies.run_results import ExportError, export_run, greedy_headline

STACK_SCRIPT = Path(__file__).resolve().parents[1] / "launcher" / "stack.py"
SOAK_SCRIPT = Path(__file__).resolve().parents[1] / "labs" / "soak.py"
RESULTS_DIR = "results"
EXPORTED_RUNS = "runs"
# Keys the grid sets for each run; giving them as config flags would contradict it.
GRID_KEYS = {"run.name": "the run names", "run.seed": "--seeds", "run.runs_dir": "--runs-dir",
             "exploration.strategy": "--strategies", "replay.capacity": "--buffers",
             "pace.total_env_steps": "--updates", "evaluation.episodes_per_start": "--trials"}
POLL_S = 0.5
SOAK_EVERY_S = 60.0
FOLLOW_NICE = 15  # a curve followed beside training yields to it


@dataclass(frozen=True)
class Options:
    runs_dir: Path
    updates: int  # the budget of every run, in updates
    trials: int  # evaluation.episodes_per_start of the chosen policy's evaluation
    actors: int | None
    extra: tuple[str, ...]  # config flags for every stack and evaluation
    progress_s: float
    export: Path | None = None  # where finished runs go (deploy/studies/run_results.py); None: <runs-dir>/results/runs
    merge: tuple[Path, ...] = ()  # more folders of exported runs for the report (another machine's)
    curve_beside: bool = False  # follow the curve while the run trains (spare cores), not after

    def run_dir(self, spec: RunSpec) -> Path:
        return self.runs_dir / spec.name

    @property
    def export_dir(self) -> Path:
        return self.export if self.export is not None else self.runs_dir / RESULTS_DIR / EXPORTED_RUNS

    def run(self, spec: RunSpec) -> RunDir:
        return RunDir(self.run_dir(spec))

    def exported(self, spec: RunSpec) -> Path | None:
        """Its export, when that holds the run finished at this budget and its run folder holds nothing: a
        fresh clone or another machine, with the finished runs' exports committed, goes on to the next."""
        return None if self.run(spec).config.is_file() else self.finished_export(spec, self.export_dir)

    def finished_export(self, spec: RunSpec, exports: Path) -> Path | None:
        """The run's folder in a folder of exported runs, where that holds it finished at this budget."""
        folder = exports / spec.name
        if read_cell(folder) != {**asdict(spec), "updates": self.updates}:
            return None
        return folder if next_step(folder, run_budget(spec, self)) == DONE else None

    def steps_dir(self, spec: RunSpec) -> Path:
        """The folder whose files say the run's next step: its export where that holds it finished."""
        return self.exported(spec) or self.run_dir(spec)


# --- a run's config and commands -----------------------------------------------------------------------------

def config_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="deploy/grid/experiments.py", add_help=False,
                                     usage="deploy/grid/experiments.py [options] [config flags of deploy/launcher/stack.py --help]")
    add_config_arguments(parser)
    return parser


def identity_flags(spec: RunSpec, options: Options) -> list[str]:
    return ["--run.name", spec.name, "--run.runs_dir", str(options.runs_dir), "--run.seed", str(spec.seed),
            "--exploration.strategy", spec.strategy, "--replay.capacity", str(spec.capacity)]


def run_config(spec: RunSpec, options: Options) -> Config:
    """The run's config as its stack builds it, before the budget; a bad flag or option set fails here."""
    try:
        config = config_from_args(parse_flags(config_parser(), [*options.extra, *spec.option_flags(),
                                                                *identity_flags(spec, options)]))
    except ConfigError as error:
        raise ExperimentError(f"{spec.name}: config error: {error}") from None
    if config.pace.start_by != "steps":
        raise ExperimentError(f"{spec.name}: a budget in updates needs every strategy to start at the same env "
                              f"step (pace.start_by steps, as the drive preset has); got "
                              f"{config.pace.start_by!r}")
    if config.learner.keep_every <= 0:
        raise ExperimentError(f"{spec.name}: the grid reads a run on the policies it keeps every "
                              "learner.keep_every updates; it is 0")
    return config


def run_budget(spec: RunSpec, options: Options) -> int:
    """The run's pace.total_env_steps: its budget in updates from the env step its updates start at."""
    pace = run_config(spec, options).pace
    return budget_env_steps(pace.start_steps, pace.env_steps_per_update, options.updates)


def stack_command(spec: RunSpec, options: Options, resume: bool) -> list[str]:
    command = [sys.executable, str(STACK_SCRIPT), *options.extra, *spec.option_flags(),
               *identity_flags(spec, options), "--pace.total_env_steps", str(run_budget(spec, options))]
    command += ["--actors", str(options.actors)] if options.actors else []
    return command + (["--resume"] if resume else [])


def curve_command(run: RunDir, options: Options, *span: str) -> list[str]:
    return [sys.executable, "-m", "actor.evaluation.command", "--curve", str(run.root), *span, *options.extra]


def curve_commands(run: RunDir, options: Options) -> list[list[str]]:
    """The passes of evaluate --curve that the protocol's test curve still needs: the dense part, then the
    sparse one (a pass only where a policy it reads is missing: a pass over nothing is an error)."""
    every = keep_every(run)
    missing = curve_wanted([updates for updates, _ in run.kept_policies()], every) - curve_read(run)
    passes = []
    if any(updates <= CURVE_DENSE_UNTIL for updates in missing):
        passes.append(curve_command(run, options, "--sets", "test", "--to-updates", str(CURVE_DENSE_UNTIL),
                                    "--every", str(every)))
    if any(updates > CURVE_DENSE_UNTIL for updates in missing):
        passes.append(curve_command(run, options, "--sets", "test", "--from-updates", str(CURVE_DENSE_UNTIL + 1),
                                    "--every", str(CURVE_LATE_EVERY)))
    if not shadow_curve_done(run):  # every kind on both sets where the online curve reads, from LATE_FROM
        passes.append(curve_command(run, options, "--kinds", ",".join(late_kinds(run)), "--sets", "train,test",
                                    "--from-updates", str(LATE_FROM), "--every", str(every)))
    return passes


def follow_command(run: RunDir, options: Options) -> list[str]:
    """The test curve followed beside training, on one worker at low priority (--curve-beside)."""
    return curve_command(run, options, "--sets", "test", "--follow", "--nice", str(FOLLOW_NICE),
                         "--evaluation.workers", "1", "--every", str(CURVE_LATE_EVERY))


def choice_commands(run: RunDir, options: Options) -> list[list[str]]:
    """The passes on the train starts that the choice still needs, of every kept kind: its candidates on the
    schedule, then the last policy where that is off it; a policy kept at a stop among them is not read."""
    passes, every = [], keep_every(run)
    for kind in ["online", *shadow_kinds(run)]:
        candidates = choice_candidates(run, kind)
        if not candidates:
            raise ExperimentError(f"{run.root}: no kept {kind} policy to choose among (learner.keep_every was 0)")
        missing = set(candidates) - curve_read(run, "train", kind)
        if any(updates % every == 0 for updates in missing):
            passes.append(curve_command(run, options, "--kinds", kind, "--sets", "train", "--from-updates",
                                        str(candidates[0]), "--every", str(every)))
        if any(updates % every for updates in missing):
            passes.append(curve_command(run, options, "--kinds", kind, "--sets", "train", "--from-updates",
                                        str(candidates[-1])))
    return passes


def evaluate_commands(run: RunDir, options: Options) -> list[list[str]]:
    """Each kind's chosen policy not yet evaluated, on both start sets, into evaluation/ (online, with the
    random baseline) or evaluation-<kind>/."""
    choice = read_choice(run)
    return [[sys.executable, "-m", "actor.evaluation.command", "--checkpoint", str(run.policy(chosen_updates(choice, kind), kind)),
             "--out", str(run.evaluation_of(kind)), *([] if kind == "online" else ["--no-random-baseline"]),
             *options.extra, "--evaluation.episodes_per_start", str(options.trials)] for kind in to_evaluate(run, choice)]


def check_config_flags(specs: list[RunSpec], options: Options) -> None:
    """Builds every run's config as the stack will, so a bad flag fails here and not after an hour."""
    for token in options.extra:
        key = token.removeprefix("--").split("=")[0]
        if key in GRID_KEYS:
            raise ExperimentError(f"--{key} is set by the grid for each run ({GRID_KEYS[key]}); do not pass it")
    for spec in specs:
        run_config(spec, options)


# --- one run ------------------------------------------------------------------------------------------------------

@dataclass
class RunJob:
    """One run of the grid, stepped through its steps (deploy/grid/grid_cells.py) on its own thread."""

    number: int
    total: int
    spec: RunSpec
    options: Options
    stopping: threading.Event
    phase: str = "waiting"
    children: list[Child] = field(default_factory=list)
    error: str | None = None
    headline: str = ""
    trained_at_start: float = 0.0  # the share of its budget its checkpoint held when the grid started
    took_s: float | None = None  # wall time of its steps, once it ran them in this session
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
        self.children = []

    @property
    def run(self) -> RunDir:
        return self.options.run(self.spec)

    def _steps(self) -> None:
        budget, done = run_budget(self.spec, self.options), []
        if (exported := self.options.exported(self.spec)) is not None:
            self.phase, self.headline = "already exported", evaluation_headline(RunDir(exported))
            print(f"{self.tag}: finished and exported to {exported}; nothing to run (remove that folder to train "
                  "it again)", flush=True)
            return
        if self.run.config.is_file() and read_cell(self.run.root) is None:  # a run started by hand
            write_cell(self.run, self.spec, self.options.updates)
        if (killed := close_killed_step(self.run)) is not None:
            print(f"{self.tag}: its last {killed} step ended without a word (its runner was killed); "
                  f"recorded as killed, and it goes on from what its folder holds", flush=True)
        while (step := next_step(self.run.root, budget)) != DONE:
            if done and done[-1] == step:
                raise ExperimentError(f"the {step} step left the run as it was; see {self.run.logs}/")
            print(f"{self.tag}: {step}", flush=True)
            self.phase, started, outcome = step, time.time(), "failed"
            open_step(self.run, step, started)
            peak = TreePeak(lambda: [child.process.pid for child in list(self.children)]).start()
            try:
                {TRAIN: self._train, RESUME: self._train, CURVE: self._curve, CHOOSE: self._choose,
                 EVALUATE: self._evaluate}[step](step)
                outcome = "done"
            finally:
                record_step(self.run, step, started, "stopped" if self.stopping.is_set() else outcome, peak.stop())
            done.append(step)
        self.phase, self.headline = "done" if done else "already done", evaluation_headline(self.run)
        if done:
            self.took_s = time.monotonic() - self.started
        try:
            print(f"{self.tag}: exported to {export_run(self.run, self.options.export_dir)}", flush=True)
        except ExportError as error:
            raise ExperimentError(f"cannot export: {error}") from None

    def _train(self, step: str) -> None:
        if step == TRAIN:
            moved = set_aside_stale_files(self.run.root)
            if moved is not None:
                print(f"{self.tag}: an earlier attempt left no checkpoint; its logs moved to {moved}", flush=True)
            write_cell(self.run, self.spec, self.options.updates)
        stack = self._start(stack_command(self.spec, self.options, resume=step == RESUME), "stack", None, echo=True)
        beside = [(SOAK_SCRIPT, "soak")] + ([(None, "follow")] if self.options.curve_beside else [])
        while stack.process.poll() is None and beside:
            if trains_since(self.run, self.started_at):
                for script, name in beside:
                    command = ([sys.executable, str(script), str(self.run.root), "--every", str(SOAK_EVERY_S)]
                               if script else follow_command(self.run, self.options))
                    self._start(command, name, is_evaluation_line, echo=False)
                beside = []
            time.sleep(POLL_S)
        self._wait_all()
        reached = checkpoint_env_steps(self.run.checkpoint)
        if reached < run_budget(self.spec, self.options):
            raise ExperimentError(f"the stack stopped at {reached:,d} env steps, short of the budget")

    def _curve(self, _: str) -> None:
        self._passes(curve_commands(self.run, self.options))

    def _choose(self, _: str) -> None:
        self._passes(choice_commands(self.run, self.options))
        choice = choose(self.run)
        print(f"{self.tag}: chose the policy kept at {choice['updates']:,d} updates on the train starts "
              f"(train CFR {100 * choice['train_cfr']:.0f}%, among {choice['among']})", flush=True)

    def _passes(self, commands: list[list[str]]) -> None:
        for command in commands:
            self._start(command, "curve", is_evaluation_line, echo=False)
            self._wait_all()

    def _evaluate(self, _: str) -> None:
        for command in evaluate_commands(self.run, self.options):  # each summary.md, printed at its end, is in the log
            self._start(command, "evaluate", is_evaluation_line, echo=False)
            self._wait_all()

    def _start(self, command: list[str], what: str, is_status, echo: bool) -> Child:
        if self.stopping.is_set():
            raise ExperimentError("interrupted")
        child = Child(command, self.run.log(what), is_status, self.tag if echo else None)
        self.children.append(child)
        if self.stopping.is_set():  # the interruption came while the child was starting
            child.interrupt()
        return child

    def _wait_all(self) -> None:
        """Waits for every child started; raises if one failed or the grid is stopping."""
        failed = [(child, code) for child in self.children if (code := child.wait()) != 0]
        self.children = []
        if self.stopping.is_set():
            raise ExperimentError("interrupted")
        for child, code in failed:
            tail = "\n    ".join(child.tail)
            raise ExperimentError(f"{child.log_path.stem} exited with code {code} (log: {child.log_path}); "
                                  f"its last lines:\n    {tail}")

    def interrupt(self) -> None:
        for child in list(self.children):
            child.interrupt()

    def status(self) -> RunStatus | None:
        """The status file of this job's stack; None before it wrote one (an older one does not count)."""
        try:
            status = RunStatus.read(self.run.status)
        except StatusError:
            return None
        return status if status.time >= self.started_at else None

    def latest_line(self) -> str:
        """The stack's figures while training, the evaluation's status line after."""
        if self.phase in (TRAIN, RESUME):
            status = self.status()
            return stack_line(status) if status is not None else ""
        return next((child.latest for child in self.children if child.latest), "")

    def remaining_s(self) -> float | None:
        """Its stack's ETA while it trains (None if unknown yet), nothing more once it evaluates."""
        if self.phase in (TRAIN, RESUME):
            status = self.status()
            return None if status is None else status.eta_s
        return 0.0

    def trained(self) -> float:
        """The share of its budget trained, 0 to 1: its stack's while it trains, else what it had at the start."""
        if self.phase not in (TRAIN, RESUME, "waiting"):
            return 1.0
        status = self.status() if self.phase != "waiting" else None
        if status is None:
            return self.trained_at_start
        return max(self.trained_at_start, min(1.0, status.env_steps / max(status.total_env_steps, 1)))

    @property
    def tag(self) -> str:
        return f"[cell {self.number} of {self.total}] {self.spec.name}"  # numbered from 0, as --cell takes them

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


def evaluation_headline(run: RunDir) -> str:
    """'policy 28,000 (chosen on train): test: mean length 812.4 [701.0, 905.2], CFR 35.0% [28.3, 41.7]; ...'."""
    choice = read_choice(run) or {}
    return f"policy {choice.get('updates', 0):,d} (chosen on train): " + greedy_headline(run.evaluation)
