"""A run's steps.csv: each step the grid runner took on it (train, resume, curve, choose, evaluate), when, how
long, on which machine, how it ended and the most memory it held. Summed, it is the run's machine time over
sessions and machines (deploy/studies/grid_costs.py).

A step ends in one row: done, failed, stopped (the runner was asked to stop, and its processes checkpointed),
or killed. A runner killed outright (SIGKILL: Slurm's KillWait after a requeue, the OOM killer, a lost machine)
writes nothing, so each step leaves an open mark (step.open.json) while it runs; the next runner on the folder
turns a mark it finds into a killed row, timed to the last write of the run's logs, so that no machine time
goes uncounted and the record says what happened.
"""

from __future__ import annotations

import csv
import json
import math
import os
import time
from pathlib import Path

from common.atomic_file import write_text_atomically
from common.cpu_capability import cpu_label
from common.run_dir import RunDir

STEPS_CSV = "steps.csv"
STEP_FIELDS = ("step", "started", "wall_s", "cpu", "cores", "outcome", "peak_mb")
OPEN_STEP_JSON = "step.open.json"  # the step running now; left behind only by a runner killed outright
KILLED = "killed"


def open_step(run: RunDir, step: str, started: float) -> None:
    """Marks the step as running, for close_killed_step; a mark that cannot be written is said, not raised."""
    mark = {"step": step, "started": round(started, 1), "cpu": cpu_label(), "cores": os.cpu_count()}
    try:
        write_text_atomically(run.root / OPEN_STEP_JSON, json.dumps(mark))
    except OSError as error:
        print(f"{run.root}: the {step} step is not marked as running: {error}", flush=True)


def record_step(run: RunDir, step: str, started: float, outcome: str, peak_mb: float = math.nan) -> None:
    """Appends the step's row and clears its open mark. A row that cannot be written is said, not raised: it
    must not hide the step's own outcome."""
    _append(run, {"step": step, "started": round(started, 1), "wall_s": round(time.time() - started, 1),
                  "cpu": cpu_label(), "cores": os.cpu_count(), "outcome": outcome,
                  "peak_mb": round(peak_mb) if math.isfinite(peak_mb) else ""})
    _clear_mark(run)


def close_killed_step(run: RunDir) -> str | None:
    """Turns the open mark of a runner killed outright into a killed row; the step's name, None without one.
    Its time runs to the last write in the run's logs (its processes wrote there until they died). A mark
    that does not read is removed: it holds no time worth a row."""
    path = run.root / OPEN_STEP_JSON
    try:
        mark = json.loads(path.read_text())
        step, started = str(mark["step"]), float(mark["started"])
        cpu, cores = str(mark["cpu"]), int(mark["cores"])
        if not math.isfinite(started):
            raise ValueError(f"started {started}")  # a NaN would carry into every sum of the run's hours
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError) as error:
        print(f"{run.root}: an unreadable {OPEN_STEP_JSON} is dropped: {error}", flush=True)
        _clear_mark(run)
        return None
    ended = max([started, *(_modified(item) for item in _logs(run))])
    _append(run, {"step": step, "started": round(started, 1), "wall_s": round(ended - started, 1), "cpu": cpu,
                  "cores": cores, "outcome": KILLED, "peak_mb": ""})
    _clear_mark(run)
    return step


def read_steps(folder: Path) -> list[dict]:
    """The rows of a run's steps.csv that read (step, wall_s as a float, cpu, cores; peak_mb a float, None where
    not measured); [] without one."""
    try:
        with (folder / STEPS_CSV).open(newline="") as handle:
            rows = list(csv.DictReader(handle))
    except (OSError, csv.Error, UnicodeDecodeError):
        return []
    steps = []
    for row in rows:
        try:
            steps.append({**row, "wall_s": float(row["wall_s"]), "cores": int(row["cores"]),
                          "peak_mb": _peak(row.get("peak_mb"))})
        except (KeyError, TypeError, ValueError):
            continue  # a damaged row: the others still count
    return steps


def _append(run: RunDir, row: dict) -> None:
    path = run.root / STEPS_CSV
    try:
        _current_header(path)
        with path.open("a", newline="") as handle:
            writer = csv.DictWriter(handle, fieldnames=STEP_FIELDS)
            if handle.tell() == 0:
                writer.writeheader()
            writer.writerow(row)
    except (OSError, csv.Error, UnicodeDecodeError) as error:
        print(f"{run.root}: the {row['step']} step's time is not recorded: {error}", flush=True)


def _current_header(path: Path) -> None:
    """Rewrites a steps.csv written before a column was added with today's columns, blank in its rows."""
    if not path.is_file():
        return
    with path.open(newline="") as handle:
        if next(csv.reader(handle), list(STEP_FIELDS)) == list(STEP_FIELDS):
            return
        handle.seek(0)
        rows = list(csv.DictReader(handle))
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=STEP_FIELDS, restval="", extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)


def _clear_mark(run: RunDir) -> None:
    try:
        (run.root / OPEN_STEP_JSON).unlink(missing_ok=True)
    except OSError as error:  # left, it would count this step again as killed
        print(f"{run.root}: cannot remove {OPEN_STEP_JSON}: {error}", flush=True)


def _logs(run: RunDir) -> list[Path]:
    try:
        return [item for item in run.logs.iterdir() if item.is_file()]
    except OSError:
        return []


def _modified(path: Path) -> float:
    try:
        return path.stat().st_mtime
    except OSError:
        return 0.0


def _peak(text: str | None) -> float | None:
    """A recorded peak in MB; None where blank, older than the column, or not a finite positive number."""
    try:
        value = float(text)
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) and value > 0 else None
