"""What the grid cost, for its report (deploy/studies/grid_report.py): each run's machine time (training, and
reading it: curve, choice, evaluation) from its steps.csv, and the soak across the runs (hours, restarts, each
process's memory growth and size, the largest run folder) from their soak summaries (deploy/labs/soak.py).
"""

from __future__ import annotations

import json
import math
from typing import TYPE_CHECKING, Sequence

import numpy as np

from actor.evaluation.curve import trained_with
from deploy.grid.grid_cells import counted
from deploy.grid.step_record import STEPS_CSV, read_steps

if TYPE_CHECKING:
    from deploy.studies.grid_report import GridRun

# --- machine time ------------------------------------------------------------------------------------------------

TRAINING_STEPS = ("train", "resume")  # the rest (curve, choose, evaluate) read the run


def machine_row(item: GridRun, soak_hours: float | None) -> dict:
    """A run's hours of training and of reading it (None where unknown), from its steps.csv; a run whose
    record does not start with its train step (it began before steps were recorded) takes its training hours
    from its soak, and its machines from its kept policies when it has no record at all."""
    steps = read_steps(item.run.folder)
    hours = lambda training: sum(row["wall_s"] for row in steps if (row["step"] in TRAINING_STEPS) == training) / 3600
    recorded = any(row["step"] == "train" for row in steps)
    machines = sorted({f"{row['cpu']} ({counted(row['cores'], 'core')})" for row in steps}) or (
        [f"{trained_with(item.test_rows)} (its kept policies)"] if item.test_rows else [])
    peak = lambda training: max((row["peak_mb"] for row in steps
                                 if (row["step"] in TRAINING_STEPS) == training and row["peak_mb"]), default=None)
    return {"run": item.run.name, "training_recorded": recorded,
            "training_h": hours(True) if recorded else soak_hours,
            "reading_h": hours(False) if any(row["step"] not in TRAINING_STEPS for row in steps) else None,
            "training_peak_mb": peak(True), "reading_peak_mb": peak(False), "machines": machines}


def machine_lines(rows: Sequence[dict]) -> list[str]:
    training = [row for row in rows if row["training_h"] is not None]
    reading = [row for row in rows if row["reading_h"] is not None]
    recorded = sum(row["training_recorded"] for row in training)
    machines = sorted({machine for row in rows for machine in row["machines"]})
    lines = [f"Training: {sum(row['training_h'] for row in training):.1f} h over {counted(len(training), 'run')} "
             f"({recorded} recorded step by step in {STEPS_CSV}, {len(training) - recorded} by the soak of a run "
             f"begun before). Curve, choice and evaluation: {sum(row['reading_h'] for row in reading):.1f} h over "
             f"the {counted(len(reading), 'run')} that recorded them. Machines: {'; '.join(machines) or 'unknown'}.",
             "", *_peak_lines(rows),
             "| Run | Training, h | Curve, choice and evaluation, h | Peak memory, training / reading, MB | Machines |",
             "|---|---:|---:|---:|---|"]
    for row in rows:
        hours = lambda value: "–" if value is None else f"{value:.2f}"
        megabytes = lambda value: "–" if value is None else f"{value:,.0f}"
        by_soak = " (soak)" if row["training_h"] is not None and not row["training_recorded"] else ""
        lines.append(f"| {row['run']} | {hours(row['training_h'])}{by_soak} | {hours(row['reading_h'])} | "
                     f"{megabytes(row['training_peak_mb'])} / {megabytes(row['reading_peak_mb'])} | "
                     f"{'; '.join(row['machines']) or '–'} |")
    return lines


def _peak_lines(rows: Sequence[dict]) -> list[str]:
    """The most memory a run's processes held at once (the stack's, or the curve's and evaluation's with their
    workers, summed each sample), from the runs that recorded it."""
    parts = []
    for key, what in (("training_peak_mb", "training (every role)"), ("reading_peak_mb", "curve, choice and evaluation")):
        recorded = [row for row in rows if row[key] is not None]
        if recorded:
            top = max(recorded, key=lambda row: row[key])
            parts.append(f"{what} {top[key]:,.0f} MB at most ({top['run']}; {counted(len(recorded), 'run')})")
    return [f"Peak memory of a run's processes at once: {'; '.join(parts)}.", ""] if parts else []


# --- the soak across the grid -----------------------------------------------------------------------------------

def soak_rows(runs: Sequence[GridRun], warn=print) -> list[dict]:
    """Each run's soak summary as one row; a damaged summary is left out with a line."""
    rows = []
    for item in runs:
        path = item.run.folder / "soak" / "soak_summary.json"
        if not path.is_file():
            continue
        try:
            rows.append(soak_row(item.run.name, json.loads(path.read_text())))
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as error:
            warn(f"soak left out: {path}: {type(error).__name__}: {error}")
    return rows


def soak_row(run: str, summary: dict) -> dict:
    processes = {name: figures for name, figures in summary["memory"].items() if name != "curve"}
    return {"run": run, "hours": float(summary["hours"]), "restarts": int(summary["restarts"]),
            "folder_mb": summary["folder_bytes_last"] / 1e6,
            **{f"{name}_mb_per_hour": float(figures["second_half_mb_per_hour"]) for name, figures in processes.items()},
            **{f"{name}_last_mb": float(figures["last_mb"]) for name, figures in processes.items()},
            # a soak without the replay's episodes (no snapshot manifest) has none
            "replay_rest_mb_per_hour": float((summary.get("replay_held") or {}).get("replay_rest_mb_per_hour",
                                                                                   math.nan))}


def soak_lines(rows: Sequence[dict]) -> list[str]:
    if not rows:
        return ["No run of the grid has a soak yet."]
    processes = sorted({key for row in rows for key in row if key.endswith("_mb_per_hour")})
    largest = max(rows, key=lambda row: row["folder_mb"])
    lines = [f"{counted(len(rows), 'run')}, {sum(row['hours'] for row in rows):.1f} hours of run time in all, "
             f"{counted(sum(row['restarts'] for row in rows), 'restart')}; the largest run folder {largest['run']} "
             f"({largest['folder_mb']:,.0f} MB).", "",
             "| Process | memory growth in the second half of each run's longest session, MB/h: median | largest "
             "| memory at the run's end, MB: median | largest |", "|---|---:|---:|---:|---:|"]
    for key in processes:
        name = key.removesuffix("_mb_per_hour")
        growth, last = (_finite(rows, key), _finite(rows, f"{name}_last_mb"))
        if growth:
            ends = f"{np.median(last):,.0f} | {max(last):,.0f}" if last else "- | -"
            lines.append(f"| {name} | {np.median(growth):+.1f} | {max(growth):+.1f} | {ends} |")
    return lines


def _finite(rows: Sequence[dict], key: str) -> list[float]:
    return [row[key] for row in rows if key in row and math.isfinite(row[key])]
