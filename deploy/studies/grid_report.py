"""The grid's report, from exported runs only (deploy/studies/run_results.py), so that it rebuilds from a fresh clone
and merges runs of several machines:

- per run, on the curve's scheduled policies (grid_cells.on_schedule; not those kept at a stop): the time to
  drive (updates and env steps until the greedy test mean length first reaches 1,000 steps), where driving
  held from, the mean test length over the curve (the area under it over its span),
  and the chosen policy's test mean length and CFR with their intervals over its trials;
- per strategy (each cell of buffer and option set apart): the same over its seeds, with the paper's test CFR
  beside it, and the interquartile mean of the chosen policies' test CFR over seeds x test starts with its
  stratified bootstrap interval (common/analysis/across_seeds.py);
- the paper's two claims read by the rule of common/analysis/across_seeds.py, with the probability of
  improvement, and what the seeds can carry at all (deploy/studies/grid_claims.py);
- the buffer's claim on seed-paired runs at 1,000 and 2,000, and each run's buffer fill
  (deploy/studies/buffer_claim.py), where the grid has runs at 2,000;
- figures: the greedy test curves (median over seeds, band their range; a panel per buffer), each seed's time
  to drive, and each strategy's buffer pairs;
- what the grid cost (deploy/studies/grid_costs.py): each run's machine time, training and reading it, and its
  machines; the soak across the grid: hours, restarts, memory per process, the largest run folder.

    .venv/bin/python deploy/studies/grid_report.py results/grid/runs --out results/grid
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from actor.evaluation import EvaluationError
from actor.evaluation.curve import CURVE_CSV, DRIVE_LENGTH, first_reaching, read_curve, trained_with
from common.analysis import across_seeds
from common.analysis.intervals import Bootstrap
from common.analysis.plotting import finish_figure, pyplot
from common.analysis.tables import EPISODES_CSV, SUMMARY_CSV
from common.exploration.names import STRATEGIES
from deploy.studies import buffer_claim
from deploy.studies.comparison import read_episodes_csv
from deploy.grid.grid_cells import counted, on_schedule, read_choice
from deploy.studies.grid_claims import claims_lines
from deploy.studies.grid_costs import machine_lines, machine_row, soak_lines, soak_rows
from deploy.studies.grid_failures import failed_test_sites, prediction_lines, site_lines, start_lines
from deploy.studies.run_results import ExportedRun, collect

# The paper's test tables at buffer 1,000 (one training each, 1,000,000 steps, K = 30): test CFR in %.
PAPER_TEST_CFR = {"vdbe_softmax": 87.54, "bmc": 86.71, "max_boltzmann": 84.14, "softmax": 82.25, "vdbe": 61.77,
                  "constant": 59.79, "decreasing": 48.95}
CELL = tuple[int, str]  # replay capacity, learner option set


@dataclass
class GridRun:
    run: ExportedRun
    test_rows: list[dict]  # its greedy test curve, by updates
    choice: dict
    greedy_test: dict  # the chosen policy's greedy test row of evaluate's summary.csv
    start_cfr: np.ndarray  # its test CFR per start, by start index
    start_length: np.ndarray  # its greedy test mean length per start, by start index
    off_greedy: float = math.nan  # the share of its training actions not argmax Q (nan: not counted)
    test_sites: Counter | None = None  # its failed greedy test episodes by place (None: not recorded)

    @property
    def cell(self) -> CELL:
        return self.run.capacity, self.run.options


def read_runs(folders: Sequence[Path], warn=print) -> list[GridRun]:
    """The exported runs of the grid runner (a curve, a choice and its evaluation) in these folders."""
    runs = []
    for run in collect(folders, warn=warn):
        choice = read_choice(run.layout)
        curve = run.folder / "curve" / CURVE_CSV
        if choice is None or not curve.is_file():
            continue  # a run of the earlier comparison: deploy/studies/report.py reads it
        try:
            every = run.config.learner.keep_every
            rows = sorted((row for row in read_curve(curve)
                           if row["start_set"] == "test" and every > 0 and on_schedule(int(row["updates"]), every)),
                          key=lambda r: int(r["updates"]))
            episodes, _ = read_episodes_csv(run.layout.evaluation / EPISODES_CSV)
            greedy_test = _greedy_row(run.layout.evaluation / SUMMARY_CSV, "test")
        except (EvaluationError, ValueError, KeyError, OSError, StopIteration) as error:
            warn(f"skipped: {run.folder}: {type(error).__name__}: {error}")
            continue
        runs.append(GridRun(run, rows, choice, greedy_test, start_means(episodes, lambda e: e.collision_free),
                            start_means(episodes, lambda e: e.length), off_greedy_share(run),
                            failed_test_sites(episodes)))
    return sorted(runs, key=lambda item: (item.cell, STRATEGIES.index(item.run.strategy), item.run.seed))


def off_greedy_share(run: ExportedRun) -> float:
    """Its training.csv's share of actions not argmax Q; nan where not counted or unreadable (the figures say)."""
    try:
        curves = run.curves()
    except ValueError:
        return math.nan
    return curves.off_greedy_share if curves is not None else math.nan


def _greedy_row(summary_csv: Path, start_set: str) -> dict:
    with summary_csv.open(newline="") as handle:
        return next(row for row in csv.DictReader(handle) if row["policy"] == "greedy" and row["start_set"] == start_set)


def start_means(episodes, value) -> np.ndarray:
    """The mean of value(episode) over each test start's greedy episodes (the tasks of the statistics across
    seeds), by start index."""
    by_start: dict[int, list[float]] = {}
    for episode in episodes:
        if episode.policy == "greedy" and episode.start_set == "test":
            by_start.setdefault(episode.start_index, []).append(value(episode))
    return np.asarray([np.mean(by_start[start]) for start in sorted(by_start)], dtype=float)


def curve_mean(rows: Sequence[dict]) -> float:
    """The mean test length over the curve's span of updates: the area under it (trapezoids) over the span,
    so that a curve read more sparsely late is not weighted by its number of points."""
    updates = np.asarray([int(row["updates"]) for row in rows], dtype=float)
    lengths = np.asarray([float(row["mean_length"]) for row in rows])
    if len(rows) < 2:
        return float(lengths[0]) if len(rows) else math.nan
    return float(np.sum((lengths[1:] + lengths[:-1]) / 2 * np.diff(updates)) / (updates[-1] - updates[0]))


def updates_to_drive(item: GridRun) -> int | None:
    """The updates until the greedy test mean length first reached 1,000 steps; None: not by the budget."""
    drive = first_reaching(item.test_rows, "mean_length", DRIVE_LENGTH)
    return int(drive["updates"]) if drive else None


def run_row(item: GridRun) -> dict:
    drive = first_reaching(item.test_rows, "mean_length", DRIVE_LENGTH)
    held = first_reaching(item.test_rows, "mean_length", DRIVE_LENGTH, held=True)
    test = item.greedy_test
    return {
        "strategy": item.run.strategy, "capacity": item.run.capacity, "options": item.run.options,
        "seed": item.run.seed, "updates": item.run.trained_updates or "",
        "updates_to_drive": drive["updates"] if drive else "", "env_steps_to_drive": drive["env_steps"] if drive else "",
        "hours_to_drive": round(drive["wall_s"] / 3600, 2) if drive else "",
        "drive_held_from": held["updates"] if held else "",
        "curve_mean_length": round(curve_mean(item.test_rows), 1),
        "chosen_updates": item.choice["updates"],
        "test_mean_length": float(test["mean_length"]), "test_mean_length_low": float(test["mean_length_low"]),
        "test_mean_length_high": float(test["mean_length_high"]),
        "test_cfr": float(test["cfr"]), "test_cfr_low": float(test["cfr_low"]), "test_cfr_high": float(test["cfr_high"]),
        # a policy looping one block reaches the cap too: turning right wherever it can covers 6 streets
        "test_streets": float(test.get("mean_streets") or "nan"),
        "test_junctions": float(test.get("mean_junctions") or "nan"),
        "trained_on": trained_with(item.test_rows) if item.test_rows else "",
        "off_greedy_share": round(item.off_greedy, 4) if math.isfinite(item.off_greedy) else "",
    }


def strategy_rows(runs: Sequence[GridRun], bootstrap: Bootstrap) -> list[dict]:
    rows = []
    for cell in sorted({item.cell for item in runs}):
        for strategy in STRATEGIES:
            seeds = [item for item in runs if item.cell == cell and item.run.strategy == strategy]
            if not seeds:
                continue
            per_run = [run_row(item) for item in seeds]
            drives = [row["updates_to_drive"] for row in per_run]
            reached = sorted(value for value in drives if value != "")
            iqm = across_seeds.iqm_estimate(np.vstack([item.start_cfr for item in seeds]), bootstrap)
            iqm_length = across_seeds.iqm_estimate(np.vstack([item.start_length for item in seeds]), bootstrap)
            rows.append({
                "strategy": strategy, "capacity": cell[0], "options": cell[1], "seeds": len(seeds),
                "drove": f"{len(reached)}/{len(seeds)}",
                "updates_to_drive": ";".join(str(value) if value != "" else "not" for value in drives),
                "median_updates_to_drive": float(np.median(reached)) if len(reached) * 2 > len(seeds) else "",
                "drive_held_from": ";".join(str(row["drive_held_from"]) or "not" for row in per_run),
                "curve_mean_length": round(float(np.mean([row["curve_mean_length"] for row in per_run])), 1),
                "test_mean_length": round(float(np.mean([row["test_mean_length"] for row in per_run])), 1),
                "iqm_test_length": iqm_length.point, "iqm_test_length_low": iqm_length.interval.low,
                "iqm_test_length_high": iqm_length.interval.high,
                "test_cfr": float(np.mean([row["test_cfr"] for row in per_run])),
                "test_cfr_by_seed": ";".join(f"{row['test_cfr']:.3f}" for row in per_run),
                "iqm_test_cfr": iqm.point, "iqm_test_cfr_low": iqm.interval.low, "iqm_test_cfr_high": iqm.interval.high,
                "paper_test_cfr": PAPER_TEST_CFR[strategy] / 100 if cell == (1000, "paper") else "",
            })
    return rows


# --- figures ---------------------------------------------------------------------------------------------------

def plot_curves(runs: Sequence[GridRun], path: Path, cells: Sequence[CELL]) -> None:
    """Greedy test mean length against updates, a panel per cell: per strategy the median over seeds at the
    policies every seed has, and a band from the lowest seed to the highest."""
    plt = pyplot()
    figure, axes = plt.subplots(1, len(cells), figsize=(10 * len(cells), 5.5), dpi=90, sharey=True, squeeze=False)
    colours = dict(zip(STRATEGIES, plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    for ax, cell in zip(axes[0], cells):
        for strategy in STRATEGIES:
            seeds = [item for item in runs if item.cell == cell and item.run.strategy == strategy]
            if seeds:
                _draw_median_and_range(ax, seeds, colours[strategy], f"{strategy} ({counted(len(seeds), 'seed')})")
        ax.axhline(DRIVE_LENGTH, color="grey", linestyle=":", linewidth=1)
        ax.set(xlabel="updates", ylabel="greedy test mean length (steps)", title=f"buffer {cell[0]:,d}, {cell[1]}")
    finish_figure(plt, figure, list(axes[0]), path, "greedy test curves: median over seeds, band lowest to highest")


def _draw_median_and_range(ax, seeds: Sequence[GridRun], colour, label: str) -> None:
    shared = sorted(set.intersection(*({int(row["updates"]) for row in item.test_rows} for item in seeds)))
    values = np.asarray([[float(next(row for row in item.test_rows if int(row["updates"]) == u)["mean_length"])
                          for item in seeds] for u in shared]).reshape(len(shared), len(seeds))
    ax.plot(shared, np.median(values, axis=1), color=colour, linewidth=2, label=label)
    ax.fill_between(shared, values.min(axis=1), values.max(axis=1), color=colour, alpha=0.12, linewidth=0)


def plot_time_to_drive(rows: Sequence[dict], path: Path, budget: int) -> None:
    """Each seed's updates to drive as a dot per strategy; a seed that did not drive by the budget as an x."""
    plt = pyplot()
    figure, ax = plt.subplots(figsize=(8, 4.5), dpi=90)
    names = [name for name in STRATEGIES if any(row["strategy"] == name for row in rows)]
    for index, name in enumerate(names):
        mine = [row for row in rows if row["strategy"] == name]
        drove = [row["updates_to_drive"] for row in mine if row["updates_to_drive"] != ""]
        ax.scatter([index] * len(drove), drove, color="C0", zorder=3)
        missed = len(mine) - len(drove)
        ax.scatter([index] * missed, [budget * 1.03] * missed, marker="x", color="C3", zorder=3)
    ax.set_xticks(range(len(names)), names, rotation=20)
    ax.axhline(budget, color="grey", linestyle=":", linewidth=1)
    ax.set(ylabel="updates to drive (x: not by the budget)")
    finish_figure(plt, figure, [ax], path, "time to drive per seed: the first greedy test mean length >= 1,000")


# --- the page --------------------------------------------------------------------------------------------------

def _coverage(streets: float, junctions: float) -> str:
    return "–" if math.isnan(streets) else f"{streets:.1f} / {junctions:.1f}"


def _drive_text(value: str) -> str:
    return f"{int(value):,d}" if value.isdigit() else "not reached"


def _thousands(value) -> str:
    return "–" if value == "" or value is None else f"{int(value):,d}"


def _percent(value) -> str:
    return "–" if value == "" or value is None else f"{100 * float(value):.1f}%"


def report_lines(runs: Sequence[GridRun], bootstrap: Bootstrap) -> list[str]:
    per_run = [run_row(item) for item in runs]
    lines = ["# The grid: the exploration strategies past the knee", "",
             f"{counted(len(runs), 'run')}. Protocol: docs/experiments.md. Intervals: {100 * bootstrap.confidence:g}% "
             f"percentile, {bootstrap.replicates} bootstrap replicates.", "",
             "## Per run", "",
             "Hours to drive: the run's time until then, on the machine it names, slowed by whatever ran beside it "
             "(a test suite, a curve evaluation); across machines, compare updates.", "",
             "| Strategy | Buffer | Options | Seed | Trained updates | Updates to drive (env steps; hours) | Held from | "
             "Curve mean length | Chosen | Test mean length [CI] | Test CFR [CI] | Test streets / junctions | "
             "Trained on |",
             "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
    for row in per_run:
        drive = (f"{row['updates_to_drive']:,d} ({row['env_steps_to_drive']:,d}; {row['hours_to_drive']:.2f} h)"
                 if row["updates_to_drive"] != ""
                 else "not reached")
        lines.append(
            f"| {row['strategy']} | {row['capacity']} | {row['options']} | {row['seed']} | {_thousands(row['updates'])} | "
            f"{drive} | {_thousands(row['drive_held_from'])} | {row['curve_mean_length']:,.0f} | {row['chosen_updates']:,d} | "
            f"{row['test_mean_length']:,.0f} [{row['test_mean_length_low']:,.0f}, {row['test_mean_length_high']:,.0f}] | "
            f"{_percent(row['test_cfr'])} [{_percent(row['test_cfr_low'])}, {_percent(row['test_cfr_high'])}] | "
            f"{_coverage(row['test_streets'], row['test_junctions'])} | {row['trained_on']} |")
    lines += ["", "## Per strategy", "",
              "IQM: the interquartile mean of every seed's test starts pooled, a start's CFR (or mean length) over "
              "its trials one score (Agarwal et al. 2021). It leaves out the quarter of scores at each end, so a few "
              "starts that fail often weigh less than in a seed's CFR, and the IQM can lie above every seed's.", "",
              "| Strategy | Buffer | Options | Seeds | Drove | Updates to drive, by seed | Held from, by seed | "
              "Curve mean length | IQM test mean length [CI] | Test CFR, by seed | IQM test CFR [CI] | "
              "Paper's test CFR |",
              "|---|---:|---|---:|---:|---|---|---:|---:|---|---:|---:|"]
    for row in strategy_rows(runs, bootstrap):
        lines.append(
            f"| {row['strategy']} | {row['capacity']} | {row['options']} | {row['seeds']} | {row['drove']} | "
            f"{', '.join(_drive_text(value) for value in row['updates_to_drive'].split(';'))} | "
            f"{', '.join(_drive_text(value) for value in row['drive_held_from'].split(';'))} | "
            f"{row['curve_mean_length']:,.0f} | {row['iqm_test_length']:,.0f} {_iqm_interval(row, 'iqm_test_length')} | "
            f"{', '.join(_percent(value) for value in row['test_cfr_by_seed'].split(';'))} | "
            f"{_percent(row['iqm_test_cfr'])} {_iqm_interval(row, 'iqm_test_cfr', _percent)} | "
            f"{_percent(row['paper_test_cfr'])} |")
    lines += ["", "## Where the runs failed: the test starts", "", *start_lines(runs)]
    lines += ["", "## Where the cars crashed", "", *site_lines(runs)]
    lines += ["", "## The prediction, on the runs after it", "", *prediction_lines(runs)]
    lines += ["", "## What the strategies explored", "", *explored_lines(runs)]
    lines += ["", "## The paper's claims", "", *claims_lines(runs, bootstrap)]
    if any(item.run.capacity == buffer_claim.LARGE for item in runs):
        lines += ["", "## The buffer: 1,000 against 2,000", "",
                  *buffer_claim.buffer_lines(runs, updates_to_drive, bootstrap)]
    soaks = soak_rows(runs)
    soak_hours = {row["run"]: row["hours"] for row in soaks}
    lines += ["", "## Machine time", "", *machine_lines([machine_row(item, soak_hours.get(item.run.name))
                                                         for item in runs])]
    lines += ["", "## Soak across the grid", "", *soak_lines(soaks)]
    return lines


def explored_lines(runs: Sequence[GridRun]) -> list[str]:
    """Per strategy, each seed's share of training actions that were not argmax Q, where its actors counted."""
    counted = [item for item in runs if math.isfinite(item.off_greedy)]
    if not counted:
        return ["No run's actors counted their actions off argmax Q yet (training.csv's off_greedy)."]
    lines = ["The share of training actions that were not argmax Q, over the episodes acted wholly with the "
             "learner's weights: epsilon says how often a strategy draws an exploring action, this how often the "
             "action it took was not the greedy one (a softmax sample often is).", "",
             "| Strategy | Buffer | Options | Actions not greedy, by seed |", "|---|---:|---|---|"]
    for cell in sorted({item.cell for item in counted}):
        for strategy in STRATEGIES:
            seeds = [item for item in counted if item.cell == cell and item.run.strategy == strategy]
            if seeds:
                shares = ", ".join(f"{100 * item.off_greedy:.2f}% (seed {item.run.seed})" for item in seeds)
                lines.append(f"| {strategy} | {cell[0]} | {cell[1]} | {shares} |")
    return lines


def _iqm_interval(row: dict, name: str, text=lambda value: f"{value:,.0f}") -> str:
    # a bootstrap over one seed resamples nothing: an interval of zero width would claim a precision
    if row["seeds"] == 1:
        return "(one seed)"
    return f"[{text(row[f'{name}_low'])}, {text(row[f'{name}_high'])}]"


def write_csv(path: Path, rows: Sequence[dict]) -> Path:
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return path


def report_on(folders: Sequence[Path], out: Path, bootstrap: Bootstrap | None = None, warn=print) -> list[Path]:
    """Writes grid.md, grid_runs.csv, grid_strategies.csv, curves.png and time_to_drive.png into `out`."""
    bootstrap = bootstrap or Bootstrap()
    runs = read_runs(folders, warn)
    if not runs:
        raise ValueError("no finished grid run (with a curve, a choice and an evaluation) in "
                         + ", ".join(map(str, folders)))
    out.mkdir(parents=True, exist_ok=True)
    rows = [run_row(item) for item in runs]
    paths = [write_csv(out / "grid_runs.csv", rows), write_csv(out / "grid_strategies.csv", strategy_rows(runs, bootstrap))]
    cells = sorted({item.cell for item in runs if item.cell[1] == "paper"}) or [runs[0].cell]
    cell = cells[0]
    plot_curves(runs, out / "curves.png", cells)
    budget = max(int(item.test_rows[-1]["updates"]) for item in runs if item.test_rows)
    plot_time_to_drive([row for row in rows if (row["capacity"], row["options"]) == cell], out / "time_to_drive.png",
                       budget)
    figures = ["curves.png", "time_to_drive.png"]
    pairs = buffer_claim.buffer_pairs(runs, buffer_claim.chosen_test_cfr)
    if pairs:
        buffer_claim.plot_buffer_pairs(pairs, out / "buffer_pairs.png")
        figures.append("buffer_pairs.png")
    (out / "grid.md").write_text("\n".join(report_lines(runs, bootstrap)
                                           + [line for name in figures for line in ("", f"![{name[:-4].replace('_', ' ')}]({name})")])
                                 + "\n")
    return [out / "grid.md", *paths, *(out / name for name in figures)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="deploy/studies/grid_report.py", description=__doc__.splitlines()[0])
    parser.add_argument("folders", type=Path, nargs="+", help="folders of exported runs (the first copy of a run wins)")
    parser.add_argument("--out", type=Path, required=True, help="where grid.md, the CSVs and the figures go")
    args = parser.parse_args(argv)
    try:
        paths = report_on(args.folders, args.out, warn=lambda line: print(line, file=sys.stderr))
    except ValueError as error:
        print(f"grid_report: {error}", file=sys.stderr)
        return 1
    print((args.out / "grid.md").read_text())
    print("wrote " + ", ".join(map(str, paths)), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
