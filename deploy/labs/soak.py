"""Soak samples of a running stack: every process's memory, the run folder's size by part, and the restarts.

Beside a run of deploy/run.sh (it reads the stack's status.json for the pids), every --every seconds it
appends one row to <run>/soak/soak.csv: the run's env steps and updates, each process's resident memory
(VmRSS, MB; the stack's, and the curve's follower with its workers, `evaluate --curve RUN`), the bytes of each part of the run folder (the flight log, the replay's snapshot, checkpoints,
kept policies, logs), the bytes of the episodes the replay holds (its snapshot's manifest) and the
restarts. When the run stops (or at --until-s), it draws soak.png and writes
soak_summary.json / .md: each process's memory growth over the second half of the longest session's samples,
when the replay is full, the replay's memory growth less that of its episodes (a replay at capacity still
grows while its episodes lengthen), and the run folder's growth per hour of run time.

    .venv/bin/python deploy/labs/soak.py runs/default --every 30              # until the run stops
    .venv/bin/python deploy/labs/soak.py runs/default --report                # the figure and summary of what is there

A rerun appends to the CSV, so a resumed run's soak carries on. Its hours are the run's: a sample whose
stack time (elapsed_s) is below the one before starts a new session (a resume), and the hours between the
sessions, when nothing ran, do not count; memory growth is read in the longest session (its processes
started afresh there, and ran longest past their filling).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
import threading
import time
from pathlib import Path
from typing import Callable

import numpy as np

from common.analysis.plotting import finish_figure, pyplot
from common.run_dir import RunDir, RunStatus, StatusError
from common.shell import stop_with_parent
from deploy.launcher.console import Console
from replay.snapshot import manifest_held

PARTS = {  # the run folder's parts, by what they are
    "log": lambda run: run.wire_log_segments(),
    "snapshot": lambda run: [run.replay_snapshot],
    "checkpoints": lambda run: [run.checkpoints],
    "policies": lambda run: [run.policies],
    "process_logs": lambda run: [run.logs],
}
FIXED = ["time", "elapsed_s", "phase", "env_steps", "updates", "restarts"]
# the episodes the replay holds, by its snapshot's manifest (one snapshot period behind): what its memory
# should grow by once it is full and its episodes still lengthen
REPLAY_HELD = "bytes_replay_held"
CURVE_FOLLOWER = "curve"  # the memory column of the run's curve evaluation (evaluate --curve --follow) and workers


def resident_mb(pid: int) -> float:
    """The process's VmRSS in MB; nan if it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    return math.nan


def tree_bytes(paths: list[Path]) -> int:
    total = 0
    for path in paths:
        files = [path] if path.is_file() else path.rglob("*") if path.is_dir() else []
        for file in files:
            try:
                total += file.stat().st_size if file.is_file() else 0
            except OSError:  # a snapshot file replaced while we looked
                pass
    return total


def curve_followers(run: RunDir) -> list[int]:
    """Pids of the processes evaluating this run's curve (`evaluate --curve RUN`, the folder resolved from
    each one's working directory): they run beside the stack for as long as it trains."""
    found = []
    for proc in Path("/proc").glob("[0-9]*"):
        try:
            args = (proc / "cmdline").read_bytes().decode(errors="replace").split("\0")
            where = Path(os.readlink(proc / "cwd"))
        except OSError:  # gone, or not ours to read
            continue
        if "--curve" in args[:-1] and (where / args[args.index("--curve") + 1]).resolve() == run.root.resolve():
            found.append(int(proc.name))
    return found


def tree_resident_mb(pids: list[int]) -> float:
    """VmRSS of the processes and all their descendants (a follower's evaluation workers), MB; nan if none."""
    total, seen, todo = 0.0, set(), list(pids)
    while todo:
        pid = todo.pop()
        resident = resident_mb(pid) if pid not in seen else math.nan
        seen.add(pid)
        if math.isfinite(resident):
            total += resident
            todo += children(pid)
    return total if seen and total > 0 else math.nan


class TreePeak:
    """The largest resident memory, MB, of a changing set of processes with their descendants, summed at each
    sample (every `every_s` in a thread, from start() to stop()); nan until a sample finds one."""

    def __init__(self, pids: Callable[[], list[int]], every_s: float = 5.0) -> None:
        self.pids, self.every_s, self.peak_mb = pids, every_s, math.nan
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)

    def start(self) -> TreePeak:
        self._thread.start()
        return self

    def stop(self) -> float:
        self._stop.set()
        self._thread.join()
        return self.peak_mb

    def _watch(self) -> None:
        while True:
            now = tree_resident_mb(self.pids())
            if math.isfinite(now) and (math.isnan(self.peak_mb) or now > self.peak_mb):
                self.peak_mb = now
            if self._stop.wait(self.every_s):
                return


def children(pid: int) -> list[int]:
    """Its child processes, those of every thread (a child started from a thread is listed under that one)."""
    found = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            found += [int(child) for child in (task / "children").read_text().split()]
        except (OSError, ValueError):
            continue  # a thread that ended while we looked
    return found


def sample(run: RunDir, status: RunStatus) -> dict:
    row = {"time": round(time.time(), 1), "elapsed_s": round(status.elapsed_s, 1), "phase": status.phase,
           "env_steps": status.env_steps, "updates": status.updates, "restarts": sum(status.restarts.values())}
    row.update({f"rss_mb_{name}": round(resident_mb(pid), 1) for name, pid in sorted(status.pids.items())})
    row[f"rss_mb_{CURVE_FOLLOWER}"] = round(tree_resident_mb(curve_followers(run)), 1)
    row.update({f"bytes_{part}": tree_bytes(paths(run)) for part, paths in PARTS.items()})
    held = manifest_held(run.replay_snapshot)
    row[REPLAY_HELD] = held.bytes if held else ""
    return row


def append(path: Path, row: dict) -> None:
    """One row; a row with columns the file lacks (a soak of an older version, resumed) rewrites the file with
    them added, blank in the rows before."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fields = list(row) if not path.exists() else next(csv.reader(path.open()), list(row))
    if set(row) - set(fields):
        earlier = read_rows(path)
        fields += [name for name in row if name not in fields]
        with path.open("w", newline="") as out:
            csv.DictWriter(out, fieldnames=fields).writeheader()
            csv.DictWriter(out, fieldnames=fields).writerows(earlier)
    with path.open("a", newline="") as out:
        writer = csv.DictWriter(out, fieldnames=fields, extrasaction="ignore")
        if out.tell() == 0:
            writer.writeheader()
        writer.writerow(row)


def read_rows(path: Path) -> list[dict]:
    with path.open(newline="") as file:
        return list(csv.DictReader(file))


def slope_per_hour(hours: np.ndarray, values: np.ndarray) -> float:
    """Least-squares growth per hour; nan with fewer than two finite samples or no time between them."""
    keep = np.isfinite(values)
    if keep.sum() < 2 or np.ptp(hours[keep]) <= 0:
        return math.nan
    return float(np.polyfit(hours[keep], values[keep], 1)[0])


def memory_figures(resident: np.ndarray, hours: np.ndarray, late: np.ndarray) -> dict:
    """First, last and largest resident MB while the process was seen (nan if never), and the late growth."""
    seen = resident[np.isfinite(resident)]
    return {"first_mb": float(seen[0]) if seen.size else math.nan, "last_mb": float(seen[-1]) if seen.size else math.nan,
            "max_mb": float(seen.max()) if seen.size else math.nan,
            "second_half_mb_per_hour": slope_per_hour(hours[late], resident[late])}


def held_figures(held_mb: np.ndarray, hours: np.ndarray, late: np.ndarray, replay: dict) -> dict:
    """The replay's held episodes as memory_figures gives them, and the late growth of its memory less theirs
    (a leak shows there)."""
    figures = memory_figures(held_mb, hours, late)
    return {**figures, "replay_rest_mb_per_hour": replay["second_half_mb_per_hour"] - figures["second_half_mb_per_hour"]}


def run_hours(rows: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """Each sample's hours of run time, the gaps between sessions left out, and its session's number (a new
    session where the stack's elapsed_s falls: a resumed run's stack started again)."""
    hours, sessions = [0.0], [0]
    for before, row in zip(rows, rows[1:]):
        elapsed, earlier = float(row["elapsed_s"]), float(before["elapsed_s"])
        resumed = elapsed < earlier
        step = elapsed if resumed else float(row["time"]) - float(before["time"])
        hours.append(hours[-1] + step / 3600)
        sessions.append(sessions[-1] + resumed)
    return np.array(hours), np.array(sessions)


def longest_session(hours: np.ndarray, sessions: np.ndarray) -> int:
    """The session (stack start) that ran longest, the last of those within a minute of it: fresh processes
    grow while they fill, so a short session's second half reads as a leak (a 10-minute resume gave an actor
    +419 MB/h)."""
    spans = {session: hours[sessions == session][-1] - hours[sessions == session][0] for session in set(sessions)}
    longest = max(spans.values())
    return int(max(session for session, span in spans.items() if span >= longest - 1 / 60))


def summarize(rows: list[dict]) -> dict:
    """Memory growth of each process over the second half of the longest session, and the folder's growth per
    hour of run time."""
    hours, sessions = run_hours(rows)
    longest = longest_session(hours, sessions)
    within = sessions == longest
    late = within & (hours >= (hours[within][0] + hours[within][-1]) / 2)
    column = lambda name: np.array([float(row[name]) if row[name] not in ("", None) else math.nan for row in rows])
    processes = sorted(name[len("rss_mb_"):] for name in rows[0] if name.startswith("rss_mb_"))
    resident = {name: column(f"rss_mb_{name}") for name in processes}
    # a process never seen (no curve follower beside the run) has no figures, rather than nan ones
    memory = {name: memory_figures(mb, hours, late) for name, mb in resident.items() if not np.isnan(mb).all()}
    total = sum(column(f"bytes_{part}") for part in PARTS)
    return {"samples": len(rows), "hours": float(hours[-1]), "sessions": int(sessions[-1]) + 1,
            "growth_session": int(longest), "growth_session_hours": float(hours[within][-1] - hours[within][0]),
            "env_steps": int(float(rows[-1]["env_steps"])),
            "updates": int(float(rows[-1]["updates"])),
            "restarts": int(column("restarts")[np.append(np.diff(sessions) > 0, True)].sum()),  # each stack's last
            "memory": memory, "replay_held": (held_figures(column(REPLAY_HELD) / 2**20, hours, late, memory["replay"])
                                              if REPLAY_HELD in rows[0] and "replay" in memory else None),
            "folder_bytes_last": int(total[-1]),
            "folder_mb_per_hour": slope_per_hour(hours, total / 2**20),
            "folder_mb_per_hour_by_part": {part: slope_per_hour(hours, column(f"bytes_{part}") / 2**20)
                                           for part in PARTS}}


def longest_text(summary: dict) -> str:
    if "growth_session" not in summary:  # a summary written before the longest session was chosen
        return " of the last session"
    return f" of session {summary['growth_session'] + 1}, the longest ({summary['growth_session_hours']:.2f} h)"


def summary_text(summary: dict) -> str:
    sessions = summary.get("sessions", 1)
    lines = [f"{summary['samples']} samples over {summary['hours']:.2f} h of run time"
             f"{f' in {sessions} sessions (stack starts)' if sessions > 1 else ''}: {summary['env_steps']:,} env "
             f"steps, {summary['updates']:,} updates, {summary['restarts']} restarts",
             "", f"| process | first MB | last MB | max MB | growth, second half{longest_text(summary) if sessions > 1 else ''} "
                 "(MB/h) |", "|---|---:|---:|---:|---:|"]
    for name, memory in summary["memory"].items():
        lines.append(f"| {name} | {memory['first_mb']:.0f} | {memory['last_mb']:.0f} | {memory['max_mb']:.0f} | "
                     f"{memory['second_half_mb_per_hour']:+.1f} |")
    held = summary.get("replay_held")
    if held:
        lines += ["", f"replay's episodes (its snapshot's manifest): {held['first_mb']:.0f} MB to {held['last_mb']:.0f} MB, "
                      f"{held['second_half_mb_per_hour']:+.1f} MB/h in the second half; the replay's memory less "
                      f"them: {held['replay_rest_mb_per_hour']:+.1f} MB/h"]
    parts = ", ".join(f"{part} {rate:+.1f}" for part, rate in summary["folder_mb_per_hour_by_part"].items())
    lines += ["", f"run folder: {summary['folder_bytes_last'] / 2**20:.0f} MB at the last sample, "
                  f"{summary['folder_mb_per_hour']:+.1f} MB per hour ({parts})"]
    return "\n".join(lines) + "\n"


def draw(rows: list[dict], path: Path, title: str) -> None:
    plt = pyplot()
    figure, axes = plt.subplots(1, 3, figsize=(15, 4))
    hours, sessions = run_hours(rows)
    for name in (name for name in rows[0] if name.startswith("rss_mb_")):
        axes[0].plot(hours, [float(row[name] or "nan") for row in rows], label=name[len("rss_mb_"):])
    for part in PARTS:
        axes[1].plot(hours, [int(row[f"bytes_{part}"]) / 2**20 for row in rows], label=part)
    axes[2].step(hours, [int(row["restarts"]) for row in rows], where="post")
    for ax, label in zip(axes, ("resident memory (MB)", "run folder (MB)", "restarts")):
        for start in hours[1:][np.diff(sessions) > 0]:  # a resume: the stack started again
            ax.axvline(start, color="grey", linestyle=":", linewidth=1)
        ax.set_xlabel("hours of run time (dotted: a resume)")
        ax.set_ylabel(label)
    finish_figure(plt, figure, axes, path, title)


def report(run: RunDir, console: Console | None = None) -> dict:
    rows = read_rows(run.soak / "soak.csv")
    summary = summarize(rows)
    (run.soak / "soak_summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    (run.soak / "soak_summary.md").write_text(summary_text(summary))
    draw(rows, run.soak / "soak.png", f"soak of {run.root.name}")
    (console or Console(threading.Event())).say(summary_text(summary), end="")
    return summary


def watch(run: RunDir, every_s: float, until_s: float, stop: threading.Event, console: Console) -> None:
    """Samples until the stack stops training (after one more sample; RunStatus.training), until_s passes, or
    `stop` is set: by its grid runner gone (stop_with_parent) or its output's reader gone (Console)."""
    started = time.monotonic()
    while time.monotonic() - started < until_s and console.check():
        try:
            status = RunStatus.read(run.status)
        except StatusError as error:
            console.say(f"soak: no status yet ({error})", err=True)
        else:
            append(run.soak / "soak.csv", sample(run, status))
            console.say(f"soak: {status.phase}, {status.env_steps:,} env steps, {status.updates:,} updates")
            if not status.training():
                return
        if stop.wait(every_s):
            return


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="deploy/labs/soak.py", description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="the run folder, runs/<run>")
    parser.add_argument("--every", type=float, default=60.0, help="seconds between samples (default 60)")
    parser.add_argument("--until-s", type=float, default=math.inf, help="stop sampling after this many seconds")
    parser.add_argument("--report", action="store_true", help="only draw and summarize the samples there are")
    args = parser.parse_args(argv)
    run = RunDir(args.run)
    stop = threading.Event()
    console = Console(stop)
    if not args.report:
        stop_with_parent(stop)  # its grid runner killed: report what there is and stop
        try:
            watch(run, args.every, args.until_s, stop, console)
        except KeyboardInterrupt:  # stopped with its stack (Ctrl-C reaches the group): report what there is
            console.say("soak: stopped", err=True)
    if not (run.soak / "soak.csv").exists():
        console.say(f"soak: no samples in {run.soak}", err=True)
        return 1
    report(run, console)
    return 0


if __name__ == "__main__":
    sys.exit(main())
