"""The grid's cells and the protocol every run of them follows (docs/experiments.md).

A cell is a strategy, a replay capacity and a named learner option set (OPTION_SETS: the paper's learner, or
one of the options beyond it the study compared); a run is a cell and a seed, in <runs-dir>/<run name>/.
Every run goes through the same steps, each decided from what its folder holds, so that stopping and
running again resumes:

    train     the stack to the budget in updates (pace.total_env_steps = start_steps + updates x ratio),
              keeping a policy every learner.keep_every updates; the soak sampled beside it
    curve     the greedy test curve at CURVE_TRIALS trials per start (evaluate --curve): every policy kept on
              the keep_every schedule up to CURVE_DENSE_UNTIL updates, then those at multiples of
              CURVE_LATE_EVERY (on_schedule: not those kept when the run was stopped)
    choose    the last CHOICE_AMONG kept policies (those on the keep_every schedule, and the last) on the train
              starts; the best (train CFR, then mean length, then the later) is the run's policy, written to
              choice.json: chosen on the train starts so that its test reading is not the best of several draws
    evaluate  the chosen policy on both start sets at --trials per start (evaluate --checkpoint), into
              evaluation/

A run that keeps shadow policies (beyond the paper: learner.keep_target, learner.ema_updates) is read on
them too, each kind as a policy of its own: its curve on both start sets at every policy the online curve
reads from LATE_FROM (20,000) updates on (and the online policies' train rows there, beside them); its choice
among its last CHOICE_AMONG kept, by the same rule; that
policy's evaluation into evaluation-<kind>/. So is the mean of the last CHOICE_AMONG kept online policies
(kind mean, written at the choice to policies/mean/), at its choice point only.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from actor.evaluation.curve import CURVE_CSV, CURVE_TRIALS, LATE_FROM, chosen_on_train, read_curve
from common.analysis.tables import SUMMARY_CSV, read_facts
from common.checkpoint import Checkpoint, CheckpointError, KeptPolicy
from common.config_values import load_config
from common.schema.fields import ConfigError
from common.run_dir import POLICY_KINDS, RunDir
from deploy.tools.average_policies import average

PROTOCOL_PRESET = "drive"  # common/presets.py: 30,000 updates, updates from 28,000 env steps for every strategy
CURVE_DENSE_UNTIL = 20_000  # every kept policy up to here: where the paper's learner first drives
CURVE_LATE_EVERY = 2_000  # then at least every 2,000 updates
CHOICE_AMONG = 5  # the run's policy is chosen among its last five kept
FINAL_TRIALS = 10  # trials per start of the chosen policy's evaluation (the paper: 30)
CELL_JSON = "cell.json"  # who the run is: strategy, capacity, option set, seed, budget
CHOICE_JSON = "choice.json"

# name: (what it is, its options over the preset). Names are folder-safe; "paper" is the preset as it is.
OPTION_SETS: dict[str, tuple[str, dict[str, Any]]] = {
    "paper": ("the paper's learner", {}),
    "nstep3": ("3-step double-Q targets", {"learner.n_step": 3}),
    "stored-burnin2": ("stored LSTM state, 2 steps of burn-in", {"learner.stored_state": True, "learner.burn_in": 2}),
    "stored": ("stored LSTM state, no burn-in", {"learner.stored_state": True, "learner.burn_in": 0}),
    "batch20": ("20 traces per batch", {"learner.batch_size": 20}),
    "ratio2": ("1 update per 2 env steps", {"pace.env_steps_per_update": 2.0}),
    "bfloat16": ("bfloat16 learner (same math)", {"learner.precision": "bfloat16"}),
    "lrdecay": ("Adam's rate falling linearly to a tenth from 20,000 to 30,000 updates (beyond the paper)",
                {"learner.lr_decay_from": 20_000, "learner.lr_decay_to": 30_000, "learner.lr_final_scale": 0.1}),
    "combination": ("stored LSTM state, 2 steps of burn-in, bfloat16 where native (fast preset + stored state)",
                    {"learner.stored_state": True, "learner.burn_in": 2, "learner.precision": "auto"}),
    # issue 61's candidates for fewer updates to drive (stored-burnin2 above is another)
    "shift": ("random shift of the learner's frames, pad 4, one offset per trace (DrQ; beyond the paper)",
              {"learner.shift_pad": 4}),
    "lr3e-4": ("Adam's rate 3e-4, the gradient's norm clipped at 40 (beyond the paper)",
               {"learner.lr": 3e-4, "learner.grad_clip_norm": 40.0}),
    "start10k": ("updates from 10,000 env steps, not 28,000; decreasing epsilon's schedule not moved (beyond the "
                 "paper)", {"pace.start_steps": 10_000}),
    "bysteps": ("every trace held equally likely, not an episode uniformly then a start (beyond the paper)",
                {"replay.sample_by_steps": True}),
}

TRAIN, RESUME, CURVE, CHOOSE, EVALUATE, DONE = "train", "resume", "curve", "choose", "evaluate", "done"


class ExperimentError(RuntimeError):
    """A run or the grid cannot go on; the message says which and why."""


def run_name(strategy: str, capacity: int, seed: int, options: str = "paper") -> str:
    middle = "" if options == "paper" else f"-{options}"
    return f"{strategy}-b{capacity}{middle}-s{seed}"


@dataclass(frozen=True)
class RunSpec:
    strategy: str
    capacity: int  # replay.capacity, episodes
    seed: int
    options: str = "paper"  # a name of OPTION_SETS

    @property
    def name(self) -> str:
        return run_name(self.strategy, self.capacity, self.seed, self.options)

    def option_flags(self) -> list[str]:
        """The option set's config flags."""
        flags = []
        for key, value in OPTION_SETS[self.options][1].items():
            flags += [f"--{key}", str(value).lower() if isinstance(value, bool) else str(value)]
        return flags


def counted(number: int, noun: str) -> str:
    """"1 run", "3 runs": the grid's lines and report count runs, seeds and restarts."""
    return f"{number} {noun}{'' if number == 1 else 's'}"


def grid(strategies: list[str], capacities: list[int], seeds: list[int], option_sets: list[str] = ("paper",)
         ) -> list[RunSpec]:
    """Capacity, then option set, then seed, then strategy: a table's runs come before the next table's, and
    every strategy's first seed before any second."""
    return [RunSpec(strategy, capacity, seed, options) for capacity in capacities for options in option_sets
            for seed in seeds for strategy in strategies]


def budget_env_steps(start_steps: int, env_steps_per_update: float, updates: int) -> int:
    """pace.total_env_steps of a budget in updates, with updates from start_steps (pace.start_by steps)."""
    return int(start_steps + round(updates * env_steps_per_update))


# --- what a run holds --------------------------------------------------------------------------------------------

def checkpoint_env_steps(path: Path) -> int:
    """The learner's clock in a checkpoint: the env steps of the whole system when it was saved."""
    try:
        env_steps = Checkpoint.load(path).env_steps
    except CheckpointError as error:
        raise ExperimentError(f"cannot read the step count of {path}: {error}") from None
    if env_steps is None:
        raise ExperimentError(f"cannot read the step count of {path}: its clock has none")
    return env_steps


def on_schedule(updates: int, every: int) -> bool:
    """Whether the protocol's greedy test curve reads the policy kept at `updates` (learner.keep_every `every`):
    every kept one up to CURVE_DENSE_UNTIL, then every CURVE_LATE_EVERY, never one kept when the run was
    stopped, whose place on the curve would depend on the interruptions (an earlier time to drive)."""
    return updates % every == 0 and (updates <= CURVE_DENSE_UNTIL or updates % CURVE_LATE_EVERY == 0)


def curve_wanted(kept: list[int], every: int) -> set[int]:
    """The kept policies (by updates) the protocol's greedy test curve reads."""
    return {updates for updates in kept if on_schedule(updates, every)}


def shadow_curve_wanted(run: RunDir, kind: str) -> set[int]:
    """The kept policies of a kind (by updates) the protocol reads on both start sets where the run keeps
    shadows: those at which the online curve reads one, from LATE_FROM on."""
    kept = [updates for updates, _ in run.kept_policies(kind) if updates >= LATE_FROM]
    return curve_wanted(kept, keep_every(run))


def curve_read(run: RunDir, start_set: str = "test", kind: str = "online") -> set[int]:
    """The kept policies (by updates) of a kind the run's curve has rows of on a start set."""
    return {int(row["updates"]) for row in read_curve(run.curve / CURVE_CSV, kind) if row["start_set"] == start_set}


def shadow_kinds(run: RunDir) -> list[str]:
    """The shadow kinds the run's learner kept beside its online policies (learner.keep_target, ema_updates),
    of those it has kept files of."""
    learner = run_learner(run)
    return [kind for kind, on in (("target", learner.keep_target), ("ema", learner.ema_updates > 0))
            if on and run.kept_policies(kind)]


def chosen_kinds(run: RunDir) -> list[str]:
    """Every kind a policy is to be chosen of: online, the shadow kinds kept, and with them the mean."""
    shadows = shadow_kinds(run)
    return ["online", *shadows, *(["mean"] if shadows else [])]


def choice_candidates(run: RunDir, kind: str = "online") -> list[int]:
    """The updates of the last CHOICE_AMONG kept policies of a kind on the run's schedule (multiples of
    learner.keep_every) and of its last one: a policy kept when the run was stopped would otherwise take a
    scheduled one's place, and the candidates would depend on the interruptions."""
    kept = [updates for updates, _ in run.kept_policies(kind)]
    every = keep_every(run)
    return ([updates for updates in kept[:-1] if updates % every == 0] + kept[-1:])[-CHOICE_AMONG:]


def run_learner(run: RunDir):
    """The learner section of the run's config.toml (common.config.LearnerConfig)."""
    try:
        return load_config(toml_path=run.config).learner
    except (ConfigError, OSError, ValueError) as error:
        raise ExperimentError(f"{run.root}: cannot read its learner settings from {run.config}: {error}") from None


def keep_every(run: RunDir) -> int:
    every = run_learner(run).keep_every
    if every <= 0:
        raise ExperimentError(f"{run.root}: the grid reads a run on the policies it keeps every "
                              "learner.keep_every updates; it is 0")
    return every


def read_choice(run: RunDir) -> dict | None:
    """The run's choice.json; None when missing or not what choose() writes (made again then)."""
    try:
        choice = json.loads((run.root / CHOICE_JSON).read_text())
    except (OSError, ValueError):
        return None
    valid = (isinstance(choice, dict) and isinstance(choice.get("updates"), int)
             and isinstance(choice.get("among"), list) and isinstance(choice.get("kinds", {}), dict))
    kinds = choice.get("kinds", {}) if valid else {}
    valid = valid and all(kind in POLICY_KINDS[1:] and isinstance(chosen, dict) and isinstance(chosen.get("updates"), int)
                          for kind, chosen in kinds.items())
    return choice if valid else None


def evaluated_updates(run: RunDir, kind: str = "online") -> int | None:
    """The updates of the policy of a kind the run's evaluation read (its facts), None without one."""
    folder = run.evaluation_of(kind)
    if not (folder / SUMMARY_CSV).is_file():
        return None
    updates = str(read_facts(folder).get("updates", ""))
    return int(updates) if updates.isdigit() else None


def chosen_updates(choice: dict, kind: str = "online") -> int | None:
    """The updates of the policy of a kind that choice.json names; None where it names none of that kind."""
    chosen = choice if kind == "online" else choice.get("kinds", {}).get(kind)
    return chosen.get("updates") if isinstance(chosen, dict) else None


def to_evaluate(run: RunDir, choice: dict) -> list[str]:
    """The kinds choice.json chose a policy of that the run's evaluations have not read yet."""
    return [kind for kind in ["online", *choice.get("kinds", {})]
            if evaluated_updates(run, kind) != chosen_updates(choice, kind)]


def choice_current(run: RunDir, choice: dict) -> bool:
    """Whether choice.json chose every kind among the candidates the run's kept policies now give."""
    kinds = choice.get("kinds", {})
    return (choice.get("among") == choice_candidates(run) and list(kinds) == chosen_kinds(run)[1:]
            and all(isinstance(kinds[kind], dict) and kinds[kind].get("among") == choice_candidates(run, candidates_of(kind))
                    for kind in kinds))


def candidates_of(kind: str) -> str:
    """The kind whose kept policies a kind's choice is among: the mean is of the online ones."""
    return "online" if kind == "mean" else kind


def late_kinds(run: RunDir) -> list[str]:
    """The kinds read on both start sets late in the run: the shadow kinds and, beside them, the online one (its
    train rows there are what a kind is shipped by); none for a run without shadows."""
    shadows = shadow_kinds(run)
    return ["online", *shadows] if shadows else []


def shadow_curve_done(run: RunDir) -> bool:
    return all(shadow_curve_wanted(run, kind) <= curve_read(run, start_set, kind)
               for kind in late_kinds(run) for start_set in ("train", "test"))


def next_step(run_dir: Path, budget: int) -> str:
    """The step the run in run_dir needs next, from what it holds on disk (budget: its total env steps)."""
    run = RunDir(run_dir)
    if not run.checkpoint.is_file():
        choice = read_choice(run)
        return DONE if choice and evaluated_updates(run) is not None and not to_evaluate(run, choice) else TRAIN
    if checkpoint_env_steps(run.checkpoint) < budget:
        return RESUME  # also a run read earlier at a smaller budget
    if not curve_wanted([updates for updates, _ in run.kept_policies()], keep_every(run)) <= curve_read(run):
        return CURVE
    if not shadow_curve_done(run):
        return CURVE
    choice = read_choice(run)
    if choice is None or not choice_current(run, choice):
        return CHOOSE
    return EVALUATE if to_evaluate(run, choice) else DONE


# --- the steps' outputs ------------------------------------------------------------------------------------------

def write_cell(run: RunDir, spec: RunSpec, updates: int) -> None:
    run.root.mkdir(parents=True, exist_ok=True)
    (run.root / CELL_JSON).write_text(json.dumps({**asdict(spec), "updates": updates}, indent=1) + "\n")


def read_cell(folder: Path) -> dict | None:
    try:
        cell = json.loads((folder / CELL_JSON).read_text())
    except (OSError, ValueError):
        return None
    return cell if isinstance(cell, dict) and cell.get("options") in OPTION_SETS else None


def choose(run: RunDir) -> dict:
    """Writes choice.json: the run's policy, chosen on the train starts among its last CHOICE_AMONG kept, and
    (under "kinds") the same of each shadow kind, and the mean of the online candidates."""
    choice = choice_of(run, "online")
    kinds = {kind: choice_of(run, kind) for kind in shadow_kinds(run)}
    if kinds:
        kinds["mean"] = mean_of_candidates(run)
    choice = {**choice, **({"kinds": kinds} if kinds else {})}
    (run.root / CHOICE_JSON).write_text(json.dumps(choice, indent=1) + "\n")
    return choice


def choice_of(run: RunDir, kind: str) -> dict:
    """The kept policy of a kind chosen on the train starts among its candidates, as choice.json names it."""
    among = choice_candidates(run, kind)
    if not among:
        raise ExperimentError(f"{run.root}: no kept {kind} policy to choose among")
    rows = [row for row in read_curve(run.curve / CURVE_CSV, kind) if int(row["updates"]) in among]
    if {int(row["updates"]) for row in rows if row["start_set"] == "train"} != set(among):
        raise ExperimentError(f"{run.root}: the curve lacks train rows of the {kind} policies kept at "
                              f"{', '.join(map(str, among))}")
    chosen = chosen_on_train(rows)
    return {"updates": chosen["updates"], "kept_file": str(run.policy(chosen["updates"], kind).name), "among": among,
            "trials_per_start": CURVE_TRIALS,
            **{key: chosen[key] for key in ("train_cfr", "train_mean_length", "test_cfr", "test_mean_length")}}


def mean_of_candidates(run: RunDir) -> dict:
    """Writes the mean of the online candidates' weights to policies/mean/ (dated as the latest of them)."""
    among = choice_candidates(run)
    try:
        mean = average([KeptPolicy.load(run.policy(updates)) for updates in among])
        mean.save(run.policy(mean.updates, "mean"))
    except (CheckpointError, OSError) as error:
        raise ExperimentError(f"{run.root}: cannot average the policies kept at {among}: {error}") from None
    return {"updates": mean.updates, "kept_file": run.policy(mean.updates, "mean").name, "among": among}
