"""The comparison's report (the paper's tables 3-6 and its figures) from exported runs alone.

Each finished run of the grid is exported (deploy/studies/run_results.py): its evaluation, config, run summary and
training curves, small enough to commit. This report reads exported runs from one or more folders, merged so
that each strategy, capacity and seed counts once (the first folder listed wins), and writes into --out:
results.md and results.csv (pooled rows with bootstrap intervals over the seeds, and one row per seed, with
every run's updates) and the figures of common/analysis/figures.py and deploy/studies/performance_profile.py. No run
folder, checkpoint or log is needed: a fresh clone rebuilds the committed tables.

    .venv/bin/python deploy/studies/report.py results/comparison/runs [another-machine/runs ...] --out results/comparison
"""

from __future__ import annotations

import argparse
import datetime
import sys
from pathlib import Path
from typing import Callable, Sequence

from common.analysis.figures import (EPSILON_STRATEGIES, RunCurves, plot_epsilon, plot_loss_differences,
                                     plot_reward_bins, plot_reward_curves)
from common.analysis.intervals import Bootstrap, bootstrap_of
from common.analysis.tables import bin_labels
from deploy.studies.comparison import (PRIVILEGED, RANDOM, RESULTS_CSV, RESULTS_MD, STRATEGY_NAMES, ComparisonRow,
                               comparison_markdown, comparison_rows, write_comparison_csv)
from deploy.studies.differences import (DIFFERENCES_CSV, Difference, chances_apart, differences, differences_markdown,
                                write_differences_csv)
from deploy.studies.performance_profile import plot_performance_profiles
from deploy.studies.run_results import ExportedRun, ExportError, collect

FIGURES = {"reward_curves.png": "mean return of the last 100 training episodes",
           "epsilon.png": "epsilon against env steps (epsilon-based strategies)",
           "loss_differences.png": "|Δloss| of consecutive updates, smoothed, against updates",
           "reward_bins.png": "share of step rewards per bin, greedy policy, test starts",
           "performance_profile.png": "share of greedy episodes longer than x steps, with bootstrap bands"}


def write_report(runs: Sequence[ExportedRun], out: Path, facts: dict[str, str], bootstrap: Bootstrap | None = None,
                 warn: Callable[[str], None] = print) -> list[Path]:
    """The tables and figures of these runs into out/; returns the files written (results.md first). A run
    whose training curves cannot be read is left out of the figures, with a warning."""
    out.mkdir(parents=True, exist_ok=True)
    bootstrap = bootstrap or (bootstrap_of(runs[0].evaluation_config()) if runs else Bootstrap())
    written: list[Path] = []
    rows: list[ComparisonRow] = []
    edges: list[float] = []
    found: list[Difference] = []
    if runs:
        rows, edges = comparison_rows([run.evaluated() for run in runs], bootstrap)
        found = differences(rows, bootstrap)
        write_comparison_csv(rows, edges, out / RESULTS_CSV)
        write_differences_csv(found, out / DIFFERENCES_CSV)
        written += [out / RESULTS_CSV, out / DIFFERENCES_CSV]
    curves: list[RunCurves] = []
    for run in runs:
        try:
            run_curves = run.curves()
        except ExportError as error:
            warn(f"{run.name}: left out of the figures: {error}")
            continue
        if run_curves is not None:
            curves.append(run_curves)
    written += write_figures(curves, rows, edges, out, bootstrap)
    figures = [path.name for path in written if path.suffix == ".png"]
    (out / RESULTS_MD).write_text(results_markdown(rows, edges, facts, figures, bootstrap, found))
    return [out / RESULTS_MD, *written]


def run_facts(runs: Sequence[ExportedRun]) -> dict[str, str]:
    """What the report says of its runs, read from their configs: which, budgets, trials."""
    budgets = sorted({run.config.pace.total_env_steps for run in runs})
    trials = sorted({run.evaluation_config().evaluation.episodes_per_start for run in runs})
    return {"runs": ", ".join(run.name for run in sorted(runs, key=lambda run: (run.capacity, run.seed))) or "none",
            "budget": " or ".join(f"{budget:,d}" for budget in budgets) + " env steps per run",
            "trials": " or ".join(map(str, trials)) + " per start"}


def write_figures(curves: list[RunCurves], rows: list[ComparisonRow], edges: list[float], results: Path,
                  bootstrap: Bootstrap | None = None) -> list[Path]:
    paths = {name: results / name for name in FIGURES}
    written = []
    if curves:
        plot_reward_curves(curves, paths["reward_curves.png"])
        written.append(paths["reward_curves.png"])
        if any(run.strategy in EPSILON_STRATEGIES for run in curves):
            plot_epsilon(curves, paths["epsilon.png"])
            written.append(paths["epsilon.png"])
        plot_loss_differences(curves, paths["loss_differences.png"])
        written.append(paths["loss_differences.png"])
    panels = reward_bin_panels(rows)
    if panels:
        plot_reward_bins(panels, bin_labels(edges), paths["reward_bins.png"], FIGURES["reward_bins.png"])
        written.append(paths["reward_bins.png"])
    if rows:
        plot_performance_profiles(rows, paths["performance_profile.png"], bootstrap)
        written.append(paths["performance_profile.png"])
    return written


def reward_bin_panels(rows: list[ComparisonRow]) -> dict[str, list[tuple[str, str, tuple[float, ...]]]]:
    """Test-set rows by capacity: (name, strategy, shares) per bar, the random policy last."""
    panels: dict[str, list[tuple[str, str, tuple[float, ...]]]] = {}
    for row in rows:
        if row.start_set == "test" and row.pooled:
            panels.setdefault(f"replay capacity {row.capacity:,d}", []).append(
                (STRATEGY_NAMES[row.strategy], row.strategy, row.summary.reward_shares))
    return panels


def results_markdown(rows: list[ComparisonRow], edges: list[float], facts: dict[str, str], figures: list[str],
                     bootstrap: Bootstrap | None = None, found: Sequence[Difference] = ()) -> str:
    bootstrap = bootstrap or Bootstrap()
    level = f"{100 * bootstrap.confidence:g}%"
    lines = ["# Exploration strategies compared", ""]
    lines += [f"- {name}: {value}" for name, value in facts.items()]
    lines += ["", "Greedy policy, episodes pooled over the seeds of each strategy; the baselines, the random "
                  f"policy (uniform actions, {RANDOM!r} in results.csv) and, where an evaluation ran it, the "
                  f"privileged map-reading driver ({PRIVILEGED!r}), are the same in every table. "
                  f"Brackets hold {level} percentile intervals of {bootstrap.replicates} bootstrap replicates: "
                  "the runs (seeds) of a row drawn again whole, then each run's trials within each start "
                  "(common/analysis/intervals.py). With one seed an interval shows only the spread of the "
                  "trials; with a few seeds, read it as a guide. Updates lists every run's learner updates, "
                  "in seed order. results.csv has the pooled rows (seed \"all\") and one row per seed.", ""]
    lines += [comparison_markdown(rows, edges, bootstrap.confidence) if rows else "No run has been evaluated yet.", ""]
    compared = differences_markdown(found, bootstrap.confidence)
    if compared:
        lines += ["## Which differences the intervals support", "",
                  "Each pair of strategies on one start set and capacity (and each strategy at two capacities): "
                  f"the difference first minus second with a {level} interval of the differences of the two rows' "
                  "bootstrap replicates, the rows drawn independently (deploy/studies/differences.py). Supported: the "
                  "interval leaves out 0. With one run a side it compares two policies, not two strategies. "
                  "Runs apart: every run of one strategy, its statistic on its own episodes, beyond every run of "
                  "the other; with two seeds a run-level bootstrap narrows. By chance alone runs lie apart "
                  f"{chances_apart(found) or 'with one run a side: never asked'}. {DIFFERENCES_CSV} has every "
                  "statistic.", "", compared]
    lines += [f"![{FIGURES[name]}]({name})" for name in figures]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None, warn: Callable[[str], None] = print) -> int:
    parser = argparse.ArgumentParser(prog="deploy/studies/report.py", description=__doc__, allow_abbrev=False,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", type=Path, help="folders of exported runs, the first winning a tie")
    parser.add_argument("--out", type=Path, required=True, help="where results.md, results.csv and the figures go")
    args = parser.parse_args(argv)
    try:
        runs = collect(args.folders, warn=warn)
        if not runs:
            raise ExportError(f"no exported run in {', '.join(map(str, args.folders))}")
        facts = {**run_facts(runs), "from": ", ".join(map(str, args.folders)),
                 "date": datetime.datetime.now().isoformat(timespec="seconds")}
        paths = write_report(runs, args.out, facts, warn=warn)
    except ValueError as error:  # ExportError, ComparisonError, or data a figure cannot draw
        print(f"deploy/studies/report.py: error: {error}", file=sys.stderr)
        return 1
    print(f"{len(runs)} runs; wrote " + ", ".join(str(path) for path in paths))
    return 0


if __name__ == "__main__":
    sys.exit(main())
