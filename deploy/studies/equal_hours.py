"""What equal hours buy: the greedy test curves of runs that trained on one CPU model, read at equal measured
wall time (issue 25: the long run beside the paper's method).

The study (deploy/studies/study.py) compares configurations at equal updates and derives their wall time, since its
runs trained on different CPUs in different sessions. Runs that each trained alone on one CPU model can be read
at equal measured hours instead. At each mark, every run gives the last kept policy it had by then, and the
mean over the policies it kept in the span before the mark: a greedy curve swings by hundreds of steps
between neighbouring policies, so one reading can be luck.

    .venv/bin/python deploy/studies/equal_hours.py results/long-run/study-combination-s0 \\
        results/long-run/study-paper-s0 --out results/long-run/equal-hours
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from actor.evaluation.curve import DRIVE_LENGTH, MILESTONES, first_reaching
from common.analysis.plotting import finish_figure, pyplot
from common.eta import clock_time
from deploy.studies.study import StudyRun, find_runs

SPAN_S = 1800.0  # the marks' spacing, and the span each mark's mean reads


def one_cpu(runs: Sequence[StudyRun]) -> str:
    """The CPU model every run trained on. Measured hours on two models do not compare (one was twice as fast
    as the other in this project's sessions): the study's derived wall time is the way there."""
    models = {row["trained_on"] for run in runs for row in run.test_rows}
    if len(models) != 1:
        raise SystemExit("equal_hours: the runs trained on " + " and ".join(sorted(models)) + "; measured hours "
                         "compare only on one CPU model (deploy/studies/study.py derives wall time instead)")
    return models.pop()


def reading_at(run: StudyRun, mark_s: float, span_s: float) -> dict | None:
    """The run at `mark_s` seconds: its last kept policy by then and the mean over those of the span before;
    None before its first reading, or past its last (the policy it stopped with): it did not train that long."""
    by_then = [row for row in run.test_rows if float(row["wall_s"]) <= mark_s]
    if not by_then or float(run.test_rows[-1]["wall_s"]) < mark_s:
        return None
    last = by_then[-1]
    span = [row for row in by_then if float(row["wall_s"]) > mark_s - span_s] or [last]
    return {"updates": int(last["updates"]), "env_steps": int(last["env_steps"]), "wall_s": float(last["wall_s"]),
            "mean_length": float(last["mean_length"]), "mean_length_low": float(last["mean_length_low"]),
            "mean_length_high": float(last["mean_length_high"]), "cfr": float(last["cfr"]),
            "span_policies": len(span),
            "span_mean_length": float(np.mean([float(row["mean_length"]) for row in span])),
            "span_cfr": float(np.mean([float(row["cfr"]) for row in span]))}


def marks(runs: Sequence[StudyRun], span_s: float) -> list[float]:
    """Every span up to the longest run's last reading, and each run's last reading: where it stopped."""
    ends = {float(run.test_rows[-1]["wall_s"]) for run in runs}
    return sorted(ends | {span_s * k for k in range(1, int(max(ends) // span_s) + 1)})


def label(run: StudyRun) -> str:
    return f"{run.configuration}, seed {run.seed}"


def hours_rows(runs: Sequence[StudyRun], span_s: float) -> list[dict]:
    return [{"mark_s": round(mark, 1), "configuration": run.configuration, "seed": run.seed,
             **(reading_at(run, mark, span_s) or {})} for mark in marks(runs, span_s) for run in runs]


def milestone_lines(run: StudyRun) -> list[str]:
    lines = []
    for _, column, threshold, held, what in MILESTONES:
        if held:
            continue
        reached = first_reaching(run.test_rows, column, threshold)
        lines.append(f"{label(run)}: first {what} " + (
            f"at {clock_time(reached['wall_s'])} ({reached['updates']:,d} updates, {reached['env_steps']:,d} env steps)"
            if reached else f"not reached by {clock_time(float(run.test_rows[-1]['wall_s']))}"))
    return lines


def plot_hours(runs: Sequence[StudyRun], path: Path, cpu: str) -> None:
    """Test mean length (its band the trials' interval) and CFR of each run against measured hours."""
    plt = pyplot()
    figure, axes = plt.subplots(1, 2, figsize=(11, 4.2), dpi=90)
    for run in runs:
        hours = np.asarray([float(row["wall_s"]) / 3600 for row in run.test_rows])
        column = {name: np.asarray([float(row[name]) for row in run.test_rows])
                  for name in ("mean_length", "mean_length_low", "mean_length_high", "cfr")}
        line, = axes[0].plot(hours, column["mean_length"], marker=".", linewidth=1.2, label=label(run))
        axes[0].fill_between(hours, column["mean_length_low"], column["mean_length_high"], color=line.get_color(),
                             alpha=0.15, linewidth=0)
        axes[1].plot(hours, 100 * column["cfr"], marker=".", linewidth=1.2, color=line.get_color(), label=label(run))
    axes[0].axhline(DRIVE_LENGTH, color="grey", linestyle=":", linewidth=1)
    axes[0].set(xlabel="measured wall time (h)", ylabel="greedy test mean length (steps)")
    axes[1].set(xlabel="measured wall time (h)", ylabel="greedy test CFR (%)")
    finish_figure(plt, figure, axes, path, f"equal hours on {cpu}: greedy test curves (K = 5 trials per start)")


def cell(row: dict, name: str) -> str:
    if "updates" not in row:
        return "–"
    if name == "last":
        return (f"{row['mean_length']:,.0f} [{row['mean_length_low']:,.0f}, {row['mean_length_high']:,.0f}], "
                f"CFR {100 * row['cfr']:.0f}% ({row['updates']:,d} updates)")
    return f"{row['span_mean_length']:,.0f}, CFR {100 * row['span_cfr']:.0f}% ({row['span_policies']})"


def write_report(runs: Sequence[StudyRun], span_s: float, out: Path) -> Path:
    cpu = one_cpu(runs)
    rows = hours_rows(runs, span_s)
    out.mkdir(parents=True, exist_ok=True)
    columns = list(dict.fromkeys(key for row in rows for key in row))
    with (out / "equal_hours.csv").open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=columns, restval="")
        writer.writeheader()
        writer.writerows(rows)
    plot_hours(runs, out / "equal_hours.png", cpu)
    names = [label(run) for run in runs]
    lines = [f"# Equal hours on {cpu}", "",
             f"Greedy test curves (K = 5 trials per start) read at measured wall time, every {span_s / 60:.0f} min. "
             f"Each cell: the last kept policy by the mark, its mean length [95% CI] and CFR; then the mean over the "
             f"policies kept in the {span_s / 60:.0f} min before it (how many). – where a run had not started reading "
             "or had stopped.", "",
             "| wall time | " + " | ".join(f"{name}: last | {name}: span mean" for name in names) + " |",
             "|---|" + "---:|" * (2 * len(names))]
    for mark in marks(runs, span_s):
        at = [row for row in rows if row["mark_s"] == round(mark, 1)]
        lines.append(f"| {clock_time(mark)} | " + " | ".join(f"{cell(row, 'last')} | {cell(row, 'span')}"
                                                            for row in at) + " |")
    lines += ["", *[f"- {line}" for run in runs for line in milestone_lines(run)], "",
              "Runs: " + ", ".join(f"{label(run)} ({run.folder})" for run in runs) + "."]
    (out / "equal_hours.md").write_text("\n".join(lines) + "\n")
    return out / "equal_hours.md"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="equal_hours", description=__doc__.splitlines()[0])
    parser.add_argument("folders", type=Path, nargs="+", help="run folders with config.toml and a greedy curve "
                        "(as the study exported them, or a run folder)")
    parser.add_argument("--every-min", type=float, default=SPAN_S / 60,
                        help=f"minutes between marks, and the span each mark's mean reads (default {SPAN_S / 60:.0f})")
    parser.add_argument("--out", type=Path, required=True,
                        help="where equal_hours.md, equal_hours.csv and equal_hours.png go")
    args = parser.parse_args(argv)
    if not (args.every_min > 0 and math.isfinite(args.every_min)):
        parser.error(f"--every-min must be a positive number of minutes, not {args.every_min}")
    runs = [run for run in find_runs(args.folders) if run.test_rows]
    if len(runs) < 2:
        raise SystemExit(f"equal_hours: {len(runs)} run(s) with a greedy test curve in "
                         + ", ".join(map(str, args.folders)) + "; two or more compare")
    try:
        print(write_report(runs, 60 * args.every_min, args.out).read_text())
    except (KeyError, ValueError) as error:  # a curve that is not evaluate --curve's: one line, not a trace
        raise SystemExit(f"equal_hours: a curve lacks a column or holds a bad value ({type(error).__name__}: "
                         f"{error}); regenerate it with evaluate --curve") from None


if __name__ == "__main__":
    sys.exit(main())
