"""The buffer's history rebuilt from a run's episodes in order (training.csv: one row per episode, as the actor
sent them), for runs whose replay kept no fill counters (replay/buffer_fill.py came later).

The store's rules replayed: an episode shorter than a trace is not stored; the oldest goes when one more than
replay.capacity is held; a batch draws its episodes uniformly (replay/store.py), so a served step comes from
the random phase with the share of held episodes weighted by the share of their steps acted before updates
started (pace.start_steps). Updates are taken to run at the configured pace from the start, env steps past the
start over pace.env_steps_per_update, which the grid's achieved ratios (4.0 +- 0.05) bear out.

    .venv/bin/python deploy/studies/buffer_history.py results/grid/runs --capacities 1000,2000
"""

from __future__ import annotations

import argparse
import csv
import sys
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from common.config_values import load_config


@dataclass(frozen=True)
class BufferHistory:
    capacity: int
    stored: int  # episodes stored in all
    random_stored: float  # of them, the random phase's (a straddling episode by its share of steps)
    full_at_env_steps: int | None  # None: never full
    full_at_updates: int | None
    served_random_share: float  # over every update
    served_random_share_after_full: float | None
    held_random_share_end: float  # the random phase's share of the episodes held at the end


def random_shares(lengths: np.ndarray, start_steps: int) -> np.ndarray:
    """Per episode, the share of its steps acted before env step start_steps (the episodes in order)."""
    ends = np.cumsum(lengths)
    begins = ends - lengths
    return np.clip((start_steps - begins) / np.maximum(lengths, 1), 0.0, 1.0)


def rebuild(lengths: Sequence[int], capacity: int, trace_length: int, start_steps: int,
            steps_per_update: float) -> BufferHistory:
    """The store's history over these episodes: what it held after each, and what each update drew."""
    lengths = np.asarray(lengths, dtype=np.int64)
    ends = np.cumsum(lengths)
    shares = random_shares(lengths, start_steps)
    kept = lengths >= trace_length
    held_random, full_at = 0.0, None
    held: deque[float] = deque()
    served_updates = served_random = after_updates = after_random = 0.0
    updates_before = 0.0
    for end, share, stored in zip(ends, shares, kept):
        # the updates made while this episode ran drew from the store as it was before it came
        updates_now = max(0.0, (end - start_steps) / steps_per_update)
        made, mix = updates_now - updates_before, (held_random / len(held) if held else 0.0)
        updates_before = updates_now
        served_updates, served_random = served_updates + made, served_random + made * mix
        if full_at is not None:
            after_updates, after_random = after_updates + made, after_random + made * mix
        if stored:
            held.append(float(share))
            held_random += share
            if len(held) > capacity:
                held_random = max(0.0, held_random - held.popleft())
            if full_at is None and len(held) == capacity:
                full_at = int(end)
    return BufferHistory(
        capacity, int(kept.sum()), float((shares * kept).sum()), full_at,
        None if full_at is None else int(max(0.0, (full_at - start_steps) / steps_per_update)),
        served_random / served_updates if served_updates else 0.0,
        after_random / after_updates if after_updates else None,
        held_random / len(held) if held else 0.0)


def read_lengths(training_csv: Path) -> list[int]:
    with training_csv.open(newline="") as handle:
        return [int(row["length"]) for row in csv.DictReader(handle)]


def history_lines(rows: Sequence[tuple[str, BufferHistory]]) -> list[str]:
    lines = ["| Run | Buffer | Episodes stored (random phase) | Full at env steps (updates) | Random-phase share "
             "served: all updates (after the fill) | Held at the end |", "|---|---:|---:|---|---|---:|"]
    for name, found in rows:
        full = "never" if found.full_at_env_steps is None else f"{found.full_at_env_steps:,d} ({found.full_at_updates:,d})"
        after = "–" if found.served_random_share_after_full is None else f"{100 * found.served_random_share_after_full:.1f}%"
        lines.append(f"| {name} | {found.capacity:,d} | {found.stored:,d} ({found.random_stored:,.0f}) | {full} | "
                     f"{100 * found.served_random_share:.1f}% ({after}) | {100 * found.held_random_share_end:.1f}% |")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="deploy/studies/buffer_history.py", description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path, help="exported runs, each with training.csv and config.toml")
    parser.add_argument("--capacities", default="", help="comma-separated buffers to replay each run's episodes "
                        "through (default: each run's own replay.capacity)")
    args = parser.parse_args(argv)
    rows = []
    for run in sorted(path.parent for path in args.folder.glob("*/training.csv")):
        try:
            config = load_config(toml_path=run / "config.toml")
            lengths = read_lengths(run / "training.csv")
        except (OSError, ValueError, KeyError) as error:
            print(f"skipped: {run}: {error}", file=sys.stderr)
            continue
        capacities = [int(value) for value in args.capacities.split(",") if value] or [config.replay.capacity]
        rows += [(run.name, rebuild(lengths, capacity, config.learner.trace_length, config.pace.start_steps,
                                    config.pace.env_steps_per_update)) for capacity in capacities]
    if not rows:
        print(f"buffer_history: no run with training.csv and config.toml in {args.folder}", file=sys.stderr)
        return 1
    print("\n".join(history_lines(rows)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
