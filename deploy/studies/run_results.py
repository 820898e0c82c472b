"""A finished run's small outputs, kept where its run folder is not: committed with the code, or brought from
another machine, so that the comparison's report rebuilds from them alone (deploy/studies/report.py).

An exported run is a folder <strategy>-b<capacity>-s<seed>/ that holds what the tables and figures read and
nothing large:

    config.toml      the run's resolved config, which says who the run is: strategy, replay capacity, seed
    summary.json     the run summary: updates, env steps, achieved env steps per update, restarts
    evaluation/      evaluate's episodes.csv, summary.csv, summary.md, facts.json and config.toml
    evaluation-<kind>/  the same of the run's chosen policy of another kind (target, ema, mean), where it has them
    training.csv     one row per training episode, in the order the episodes ended: return, length, epsilon,
                     off_greedy (actions not argmax Q; -1 where not counted; absent in older exports)
    learner.csv      one row per learner report: updates, |loss_k - loss_k-1|
    cell.json        a grid run's cell: strategy, capacity, learner option set, seed, budget (deploy/grid/grid_cells.py)
    choice.json      a grid run's policy, chosen on the train starts among its last kept
    curve/           its greedy curve: curve.csv, curve_summary.json and .md, curve.png
    soak/            its soak: soak.csv, soak_summary.json and .md, soak.png (deploy/labs/soak.py)

Checkpoints, replay snapshots and MCAP logs stay in the run folder. A run is known by its strategy, capacity,
learner option set and seed, so runs exported on several machines merge into one set (collect) and none
counts twice.
"""

from __future__ import annotations

import csv
import filecmp
import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

from actor.evaluation.curve import CURVE_CSV, CURVE_PNG, SUMMARY_JSON
from actor.evaluation.curve import SUMMARY_MD as CURVE_SUMMARY_MD
from common.analysis.figures import RunCurves
from common.analysis.tables import EPISODES_CSV, FACTS_JSON, SUMMARY_CSV, SUMMARY_MD, read_facts
from common.config import Config
from common.config_values import load_config
from common.schema.fields import ConfigError
from common.run_dir import POLICY_KINDS, RunDir
from deploy.studies.comparison import EvaluatedRun
from deploy.grid.grid_cells import CELL_JSON, CHOICE_JSON, read_cell, run_name
from deploy.grid.step_record import STEPS_CSV
from replay.recorder.reader import LogError
from replay.recorder.run_curves import read_run_curves

CONFIG_TOML = "config.toml"  # evaluate's copy of its config, in evaluation/
TRAINING_CSV = "training.csv"
LEARNER_CSV = "learner.csv"
EVALUATION_FILES = (EPISODES_CSV, SUMMARY_CSV, SUMMARY_MD, FACTS_JSON, CONFIG_TOML)
# a grid run's files (deploy/grid/experiments.py), by their path in the run folder and in the export
GRID_FILES = (CELL_JSON, CHOICE_JSON, STEPS_CSV, *(f"curve/{name}" for name in (CURVE_CSV, SUMMARY_JSON, CURVE_SUMMARY_MD,
                                                                      CURVE_PNG)),
              *(f"soak/{name}" for name in ("soak.csv", "soak.png", "soak_summary.json", "soak_summary.md")))
TRAINING_COLUMNS = ("return", "length", "epsilon", "off_greedy")
OLDER_TRAINING_COLUMNS = TRAINING_COLUMNS[:3]  # exports from before off_greedy was counted
LEARNER_COLUMNS = ("updates", "loss_abs_diff")


class ExportError(ValueError):
    """A run cannot be exported, or an exported folder cannot be read; the message says which and why."""


@dataclass(frozen=True)
class ExportedRun:
    folder: Path
    config: Config

    @property
    def layout(self) -> RunDir:
        return RunDir(self.folder)

    @property
    def strategy(self) -> str:
        return self.config.exploration.strategy

    @property
    def capacity(self) -> int:
        return self.config.replay.capacity

    @property
    def seed(self) -> int:
        return self.config.run.seed

    @property
    def options(self) -> str:
        """Its learner option set (cell.json; runs from before the grid runner: the paper's learner)."""
        cell = read_cell(self.folder)
        return cell["options"] if cell else "paper"

    @property
    def identity(self) -> tuple[str, int, int, str]:
        return self.strategy, self.capacity, self.seed, self.options

    @property
    def name(self) -> str:
        return run_name(*self.identity)

    @property
    def updates(self) -> int | None:
        """The updates of the weights its evaluation used, else of the run summary (None if neither says)."""
        updates = str(read_facts(self.layout.evaluation).get("updates", ""))
        return int(updates) if updates.isdigit() else self.trained_updates

    @property
    def trained_updates(self) -> int | None:
        """The updates the run trained, from its run summary (None if it does not say)."""
        try:
            updates = json.loads(self.layout.summary.read_text()).get("updates")
        except (OSError, ValueError, AttributeError):
            return None
        return updates if isinstance(updates, int) and not isinstance(updates, bool) else None

    def evaluation_config(self) -> Config:
        """The config its evaluation ran with (trials, caps, bootstrap), else the run's."""
        path = self.layout.evaluation / CONFIG_TOML
        return _read_config(path) if path.is_file() else self.config

    def evaluated(self) -> EvaluatedRun:
        return EvaluatedRun(self.strategy, self.capacity, self.layout.evaluation, self.seed, self.updates)

    def curves(self) -> RunCurves | None:
        """Its training curves, or None if it was exported without logs."""
        if not (self.folder / TRAINING_CSV).is_file():
            return None
        curves = RunCurves(self.name, self.strategy, self.capacity)
        try:
            for row in _read_rows(self.folder / TRAINING_CSV, TRAINING_COLUMNS, OLDER_TRAINING_COLUMNS):
                curves.episode_returns.append(float(row["return"]))
                curves.episode_lengths.append(int(row["length"]))
                curves.episode_epsilons.append(float(row["epsilon"]))
                curves.episode_off_greedy.append(int(row.get("off_greedy", -1)))
            for row in _read_rows(self.folder / LEARNER_CSV, LEARNER_COLUMNS):
                curves.learner_updates.append(float(row["updates"]))
                curves.loss_abs_diffs.append(float(row["loss_abs_diff"]))
        except (TypeError, ValueError) as error:
            if isinstance(error, ExportError):
                raise
            raise ExportError(f"{self.folder}: a training curve holds a value that is not a number: {error}") from None
        return curves


def export_run(run: RunDir, destination: Path) -> Path:
    """Copies an evaluated run's small outputs to destination/<run name>/, replacing an earlier export of it.

    The copy is built beside its place and renamed into it, so a reader never sees half an export."""
    if not run.config.is_file() or not (run.evaluation / SUMMARY_CSV).is_file():
        raise ExportError(f"{run.root}: not an evaluated run (it needs {run.config.name} and "
                          f"{run.evaluation.name}/{SUMMARY_CSV})")
    config, cell = _read_config(run.config), read_cell(run.root)
    folder = destination / run_name(config.exploration.strategy, config.replay.capacity, config.run.seed,
                                    cell["options"] if cell else "paper")
    staging = destination / f".{folder.name}.incoming"
    shutil.rmtree(staging, ignore_errors=True)
    copy = RunDir(staging)  # an export keeps a run folder's layout
    copy.evaluation.mkdir(parents=True)
    shutil.copy2(run.config, copy.config)
    if run.summary.is_file():
        shutil.copy2(run.summary, copy.summary)
    for kind in POLICY_KINDS:  # evaluation/, and evaluation-<kind>/ of a grid run's other kinds
        for name in EVALUATION_FILES:
            if (run.evaluation_of(kind) / name).is_file():
                copy.evaluation_of(kind).mkdir(exist_ok=True)
                shutil.copy2(run.evaluation_of(kind) / name, copy.evaluation_of(kind) / name)
    for relative in GRID_FILES:
        if (run.root / relative).is_file():
            (staging / relative).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(run.root / relative, staging / relative)
    segments = run.wire_log_segments()
    if segments:
        try:
            write_curves(read_run_curves(segments, folder.name), staging)
        except LogError as error:
            print(f"{run.root}: exported without training curves: {error}")
    if folder.exists():
        shutil.rmtree(folder)
    staging.rename(folder)
    return folder


def greedy_headline(evaluation: Path) -> str:
    """'test: mean length 812.4 [701.0, 905.2], CFR 35.0% [28.3, 41.7]; ...' from the greedy rows of an
    evaluate summary.csv (the intervals over its trials, when the file has them)."""
    with (evaluation / SUMMARY_CSV).open(newline="") as handle:
        rows = [row for row in csv.DictReader(handle) if row["policy"] == "greedy"]

    def interval(row: dict, statistic: str, scale: float) -> str:
        if not row.get(f"{statistic}_low"):
            return ""
        return f" [{scale * float(row[statistic + '_low']):,.1f}, {scale * float(row[statistic + '_high']):,.1f}]"

    return "; ".join(f"{row['start_set']}: mean length {float(row['mean_length']):,.1f}{interval(row, 'mean_length', 1)}, "
                     f"CFR {100 * float(row['cfr']):.1f}%{interval(row, 'cfr', 100)}" for row in rows)


def write_curves(curves: RunCurves, folder: Path) -> None:
    missing = len(curves.episode_returns) - len(curves.episode_off_greedy)  # curves made without the counts
    off_greedy = curves.episode_off_greedy + [-1] * missing
    _write_rows(folder / TRAINING_CSV, TRAINING_COLUMNS,
                zip(curves.episode_returns, curves.episode_lengths, curves.episode_epsilons, off_greedy))
    _write_rows(folder / LEARNER_CSV, LEARNER_COLUMNS, zip(curves.learner_updates, curves.loss_abs_diffs))


def read_exported(folder: Path) -> ExportedRun:
    layout = RunDir(folder)
    for needed in (layout.config, layout.evaluation / EPISODES_CSV):
        if not needed.is_file():
            raise ExportError(f"{folder}: not an exported run: {needed.relative_to(folder)} is missing")
    run = ExportedRun(folder, _read_config(layout.config))
    if folder.name != run.name:
        raise ExportError(f"{folder}: its config says it is run {run.name}; the folder must carry that name")
    return run


def collect(folders: Sequence[Path], warn: Callable[[str], None] = print) -> list[ExportedRun]:
    """Every exported run in these folders, each (strategy, capacity, seed) once.

    The first folder listed wins: a later copy of the same run is left out, silently if its evaluation is the
    same file, with a warning if it differs (the same grid cell trained twice). Folders that are not
    exported runs are skipped with a warning."""
    found: dict[tuple[str, int, int], ExportedRun] = {}
    for parent in folders:
        if not parent.is_dir():
            raise ExportError(f"{parent}: no such folder of exported runs")
        for folder in sorted(path for path in parent.iterdir() if path.is_dir() and not path.name.startswith(".")):
            try:
                run = read_exported(folder)
            except ExportError as error:
                warn(f"skipped: {error}")
                continue
            kept = found.setdefault(run.identity, run)
            if kept is not run and not _same_evaluation(kept, run):
                warn(f"{run.name} is in both {kept.folder.parent} and {parent} with different evaluations: "
                     f"counted once, from {kept.folder}")
    return list(found.values())


def _same_evaluation(first: ExportedRun, second: ExportedRun) -> bool:
    return filecmp.cmp(first.layout.evaluation / EPISODES_CSV, second.layout.evaluation / EPISODES_CSV,
                       shallow=False)


def _read_config(path: Path) -> Config:
    try:
        return load_config(toml_path=path)
    except (ConfigError, OSError, ValueError) as error:
        raise ExportError(f"{path}: {error}") from None


def _write_rows(path: Path, columns: Sequence[str], rows) -> None:
    with path.open("w", newline="") as stream:
        writer = csv.writer(stream)
        writer.writerow(columns)
        writer.writerows(rows)


def _read_rows(path: Path, columns: Sequence[str], older: Sequence[str] | None = None) -> list[dict[str, str]]:
    """The rows of a CSV with these columns (or an older file's columns)."""
    try:
        with path.open(newline="") as stream:
            reader = csv.DictReader(stream)
            if reader.fieldnames is None or list(reader.fieldnames) not in (list(columns), list(older or columns)):
                raise ExportError(f"{path}: expected the columns {', '.join(columns)}, got {reader.fieldnames}")
            return list(reader)
    except OSError as error:
        raise ExportError(f"{path}: {error}") from None
