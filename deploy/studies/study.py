"""The study's report (issue 24): the paper's learner and each option beyond it, 2 seeds each, read on greedy
learning curves at a fixed budget.

The study's configurations are the grid runner's learner option sets (deploy/grid/grid_cells.py OPTION_SETS); a
run of one is trained, read on its curve and exported by deploy/grid/experiments.py (`--options NAME`). The study's
own runs (results/study/runs, results/time-to-drive) were trained on the `local` preset before the runner
took over, and this report rebuilds from them. The CPU differs between sessions, so wall time is derived:
the updates a configuration needs times its seconds per update, from one run of deploy/bench/option_costs.py
on one machine.

    .venv/bin/python deploy/studies/study.py results/study/runs results/time-to-drive \\
        --costs results/option-costs/option_costs.json --out results/study

A run's configuration is read from its config.toml (the options below that it sets), not from its name, so
runs trained before the study (results/time-to-drive) count where their config puts them.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from actor.evaluation import EvaluationError
from actor.evaluation.curve import CURVE_CSV, DRIVE_LENGTH, first_reaching, read_curve
from common.analysis.plotting import finish_figure, pyplot
from common.config_values import flat_items, load_config
from common.schema.fields import ConfigError
from deploy.studies.differences import chance_apart, lie_apart
from deploy.grid.grid_cells import OPTION_SETS

ROOT = Path(__file__).resolve().parents[2]
PRESET = "local"  # the preset the study's runs were trained on
KEEP_EVERY = 1000  # updates between kept policies: the curve's resolution
# The budget: both seed-0 runs of the paper's learner first drove at about 21,000 updates (results/time-to-drive).
BUDGET_UPDATES = 21_000
CONFIGURATIONS = OPTION_SETS
STUDY_KEYS = sorted({key for _, options in CONFIGURATIONS.values() for key in options})


def configuration_of(config_items: dict[str, Any]) -> str | None:
    """The configuration whose options a run's config sets, every other study option at the preset's value;
    None for a run that fits none (a combination not in CONFIGURATIONS)."""
    baseline = flat_items(load_config(PRESET))
    for name, (_, options) in CONFIGURATIONS.items():
        wanted = {key: options.get(key, baseline[key]) for key in STUDY_KEYS}
        if all(_same(config_items.get(key), value) for key, value in wanted.items()):
            return name
    return None


def _same(found: Any, wanted: Any) -> bool:
    if isinstance(wanted, float) and isinstance(found, (int, float)):
        return math.isclose(found, wanted)
    return found == wanted


# --- report -------------------------------------------------------------------------------------------------

# the window reading: the mean over the kept policies of the last 2,000 updates to the budget, since a greedy
# curve swings by hundreds of steps between neighbouring policies (559 and 1,547 one policy apart)
READING_WINDOW = 2 * KEEP_EVERY


@dataclass
class StudyRun:
    folder: Path
    configuration: str
    seed: int
    test_rows: list[dict] = field(default_factory=list)  # the greedy test curve, by updates

    def at(self, updates: int) -> dict | None:
        """The row of the last kept policy at or before `updates`, if it was kept less than KEEP_EVERY updates
        before (a curve evaluated only in parts has no reading at the budget)."""
        rows = [row for row in self.test_rows if updates - KEEP_EVERY < int(row["updates"]) <= updates]
        return rows[-1] if rows else None

    def window(self, updates: int) -> list[dict]:
        """The rows of every kept policy from `updates` - READING_WINDOW to `updates`; none without a reading at
        `updates`, or with a policy of the window's grid not evaluated."""
        rows = [row for row in self.test_rows if updates - READING_WINDOW <= int(row["updates"]) <= updates]
        first = max(KEEP_EVERY, -(-(updates - READING_WINDOW) // KEEP_EVERY) * KEEP_EVERY)
        grid = set(range(first, updates + 1, KEEP_EVERY))  # the learner keeps a policy at each
        return rows if self.at(updates) and grid <= {int(row["updates"]) for row in rows} else []


def find_runs(folders: Sequence[Path]) -> list[StudyRun]:
    """Every run folder (holding config.toml and curve.csv) under the given folders, by configuration and seed;
    a configuration and seed found twice counts once (the first folder listed wins)."""
    found: dict[tuple[str, int], StudyRun] = {}
    for top in folders:
        for config_path in sorted(top.glob("*/config.toml")) + sorted(top.glob("config.toml")):
            folder = config_path.parent
            curve = folder / CURVE_CSV if (folder / CURVE_CSV).exists() else folder / "curve" / CURVE_CSV
            if not curve.exists():
                continue
            try:
                items = flat_items(load_config(PRESET, config_path))
                curve_rows = read_curve(curve)
            except (ConfigError, EvaluationError) as error:
                print(f"study: {folder} left out: {error}", file=sys.stderr)
                continue
            name = configuration_of(items)
            if name is None:
                print(f"study: {folder} fits no configuration of the study; left out", file=sys.stderr)
                continue
            rows = sorted((row for row in curve_rows if row["start_set"] == "test"),
                          key=lambda row: int(row["updates"]))
            found.setdefault((name, int(items["run.seed"])), StudyRun(folder, name, int(items["run.seed"]), rows))
    return sorted(found.values(), key=lambda run: (list(CONFIGURATIONS).index(run.configuration), run.seed))


def seconds_per_update(costs: Path | None) -> dict[str, float]:
    """Each configuration's median seconds per update from option_costs.json (deploy/bench/option_costs.py)."""
    if costs is None:
        return {}
    rows = json.loads(costs.read_text())["rows"]
    return {row["configuration"]: 1.0 / row["updates_per_s"] for row in rows}


def study_rows(runs: Sequence[StudyRun], budget: int, per_update: dict[str, float]) -> list[dict]:
    rows = []
    for run in runs:
        end, window = run.at(budget), run.window(budget)
        drive = first_reaching(run.test_rows, "mean_length", DRIVE_LENGTH)
        within = [row for row in run.test_rows if int(row["updates"]) <= budget]
        held = first_reaching(within, "mean_length", DRIVE_LENGTH, held=True) if end else None
        seconds = per_update.get(run.configuration)
        rows.append({
            "configuration": run.configuration, "seed": run.seed, "run": run.folder.name,
            "updates_at_budget": int(end["updates"]) if end else "",
            "test_mean_length": float(end["mean_length"]) if end else math.nan,
            "test_mean_length_low": float(end["mean_length_low"]) if end else math.nan,
            "test_mean_length_high": float(end["mean_length_high"]) if end else math.nan,
            "test_cfr": float(end["cfr"]) if end else math.nan,
            "window_mean_length": (float(np.mean([float(row["mean_length"]) for row in window])) if window
                                   else math.nan),
            "window_policies": len(window),
            "updates_to_drive": drive["updates"] if drive and drive["updates"] <= budget else "",
            # from here on every kept policy up to the budget drove: the curves swing, a first crossing can be luck
            "updates_drive_held_from": held["updates"] if held else "",
            "derived_hours_to_drive": (round(drive["updates"] * seconds / 3600, 2)
                                       if drive and seconds and drive["updates"] <= budget else ""),
            "seconds_per_update": round(seconds, 4) if seconds else "",
        })
    return rows


def supported(rows: Sequence[dict], baseline: str = "paper", column: str = "test_mean_length") -> list[str]:
    """For each configuration against the baseline: do its seeds' readings (column) lie apart, and by how much."""
    by_name: dict[str, np.ndarray] = {}
    for row in rows:
        by_name.setdefault(row["configuration"], []).append(row[column])
    if baseline not in by_name:
        return [f"no {baseline} run: nothing to compare against"]
    lines = []
    base = np.asarray(by_name[baseline], dtype=float)
    for name, values in by_name.items():
        if name == baseline:
            continue
        values = np.asarray(values, dtype=float)
        values, base_here = values[~np.isnan(values)], base[~np.isnan(base)]
        if not len(values) or not len(base_here):
            lines.append(f"{name} against {baseline}: not asked (no reading at the budget on one side)")
            continue
        gap = float(values.mean() - base_here.mean())
        apart = lie_apart(values, base_here)
        if apart is None:
            verdict = f"not asked ({len(values)} vs {len(base_here)} seeds; 2 each needed)"
        elif apart:
            verdict = (f"seeds apart (by chance alone 1 time in {round(1 / chance_apart(len(values), len(base_here)))}): "
                       "supported as a lean")
        else:
            verdict = "seeds interleave: not supported"
        lines.append(f"{name} against {baseline}: mean {gap:+,.0f} steps; {verdict}")
    return lines


def broken_at_gaps(updates: Sequence[int], values: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """The points as arrays, with a NaN between two that lie more than KEEP_EVERY updates apart: a line does
    not bridge policies that were kept but never evaluated."""
    xs, ys = [], []
    for index, (update, value) in enumerate(zip(updates, values)):
        if index and update - updates[index - 1] > KEEP_EVERY:
            xs.append(math.nan)
            ys.append(math.nan)
        xs.append(float(update))
        ys.append(float(value))
    return np.asarray(xs), np.asarray(ys)


def plot_study(runs: Sequence[StudyRun], per_update: dict[str, float], path: Path, budget: int) -> None:
    """Greedy test mean length and CFR against updates and derived wall time: a thin line per seed, a thick
    one through the seeds' mean where every seed has the policy, and a band from the lowest seed to the highest."""
    plt = pyplot()
    figure, axes = plt.subplots(2, 2, figsize=(11, 7), dpi=90)
    colours = dict(zip(CONFIGURATIONS, plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    for name in CONFIGURATIONS:
        seeds = [run for run in runs if run.configuration == name]
        if not seeds:
            continue
        for row_axes, (column, scale, label) in zip(axes, (("mean_length", 1.0, "greedy test mean length (steps)"),
                                                          ("cfr", 100.0, "greedy test CFR (%)"))):
            for ax, x_scale in zip(row_axes, (1.0, per_update.get(name, math.nan) / 3600)):
                if not math.isfinite(x_scale):
                    continue
                for run in seeds:
                    points = [row for row in run.test_rows if int(row["updates"]) <= budget]
                    xs, ys = broken_at_gaps([int(r["updates"]) for r in points], [float(r[column]) for r in points])
                    ax.plot(x_scale * xs, scale * ys, color=colours[name], alpha=0.35, linewidth=1)
                common = sorted(set.intersection(*({int(r["updates"]) for r in run.test_rows} for run in seeds)))
                common = [u for u in common if u <= budget]
                values = np.asarray([[float(next(r for r in run.test_rows if int(r["updates"]) == u)[column])
                                      for run in seeds] for u in common]).reshape(len(common), len(seeds))
                xs, ys = broken_at_gaps(common, values.mean(axis=1))
                ax.plot(x_scale * xs, scale * ys, color=colours[name], linewidth=2.2, marker=".",
                        label=f"{name} ({len(seeds)} seed{'s' if len(seeds) > 1 else ''})")
                if len(seeds) > 1:  # the seed band: from the lowest seed to the highest
                    _, low = broken_at_gaps(common, values.min(axis=1))
                    _, high = broken_at_gaps(common, values.max(axis=1))
                    ax.fill_between(x_scale * xs, scale * low, scale * high, color=colours[name], alpha=0.12,
                                    linewidth=0)
                ax.set(ylabel=label)
    for ax in axes[:, 0]:
        ax.set(xlabel="updates")
    for ax in axes[:, 1]:
        ax.set(xlabel="derived wall time (h) = updates x s/update (option_costs)")
    axes[0, 0].axhline(DRIVE_LENGTH, color="grey", linestyle=":", linewidth=1)
    finish_figure(plt, figure, axes.flat, path, "the study: greedy test curves, thin lines seeds, thick their mean, bands lowest to highest seed")


REPORT_ARGS = "study.json"  # what the report was built from, so that a test can rebuild it


def write_report(runs: Sequence[StudyRun], budget: int, costs: Path | None, out: Path,
                 folders: Sequence[Path] = ()) -> Path:
    per_update = seconds_per_update(costs)
    rows = study_rows(runs, budget, per_update)
    out.mkdir(parents=True, exist_ok=True)
    with (out / "study.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    plot_study(runs, per_update, out / "study.png", budget)
    lines = [f"# The study at {budget:,d} updates", "",
             f"Greedy test curves (K = 5 trials per start) of each configuration; wall time derived from "
             f"{costs if costs else 'no cost measurement'}.", "",
             "| Configuration | Seed | Updates read | Test mean length [95% CI] | Test CFR | "
             f"Window mean, {budget - READING_WINDOW:,d}–{budget:,d} | Updates to drive | "
             "Driving held from | Derived hours to drive | s/update |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for row in rows:
        length = ("no policy kept within 1,000 updates of the budget" if math.isnan(row["test_mean_length"]) else
                  f"{row['test_mean_length']:,.0f} [{row['test_mean_length_low']:,.0f}, "
                  f"{row['test_mean_length_high']:,.0f}]")
        cfr = "–" if math.isnan(row["test_cfr"]) else f"{100 * row['test_cfr']:.0f}%"
        window = ("–" if math.isnan(row["window_mean_length"]) else
                  f"{row['window_mean_length']:,.0f} ({row['window_policies']} policies)")
        lines.append(f"| {row['configuration']} | {row['seed']} | {row['updates_at_budget'] or '–'} | {length} | {cfr} | "
                     f"{window} | "
                     f"{row['updates_to_drive'] or 'not reached'} | {row['updates_drive_held_from'] or '–'} | "
                     f"{row['derived_hours_to_drive'] or '–'} | "
                     f"{row['seconds_per_update'] or '–'} |")
    lines += ["", "Driving held from: the first kept policy from which every one up to the budget read at least "
              f"{DRIVE_LENGTH:,.0f} steps; – where the last one before the budget read less.", "",
              "Window mean: the mean of the test mean lengths of every kept policy in the window (the curves "
              "swing between neighbouring policies); – where one of the window's policies was not evaluated.", "",
              "Which differences the seeds support, at the budget:", ""]
    lines += [f"- {line}" for line in supported(rows)]
    lines += ["", f"And over the window, {budget - READING_WINDOW:,d}–{budget:,d} updates:", ""]
    lines += [f"- {line}" for line in supported(rows, column="window_mean_length")]
    (out / "study.md").write_text("\n".join(lines) + "\n")
    (out / REPORT_ARGS).write_text(json.dumps({"folders": [str(folder) for folder in folders], "budget": budget,
                                               "costs": str(costs) if costs else None}, indent=1) + "\n")
    return out / "study.md"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="study", description=__doc__.splitlines()[0])
    parser.add_argument("folders", type=Path, nargs="+",
                        help="folders holding exported runs or run folders; the first run of a configuration and "
                             "seed found wins")
    parser.add_argument("--budget", type=int, default=BUDGET_UPDATES,
                        help=f"read each curve at this many updates (default {BUDGET_UPDATES:,})")
    parser.add_argument("--costs", type=Path, help="option_costs.json of deploy/bench/option_costs.py")
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "study",
                        help="where study.md, study.csv, study.json and study.png go (default results/study)")
    args = parser.parse_args(argv)
    runs = find_runs(args.folders)
    if not runs:
        raise SystemExit("study: no run with a greedy curve in " + ", ".join(map(str, args.folders)))
    print(write_report(runs, args.budget, args.costs, args.out, args.folders).read_text())


if __name__ == "__main__":
    main()
