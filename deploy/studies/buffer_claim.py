"""The paper's buffer claim read on seed-paired grid runs (issue 60): the same strategy and seed at buffer 1,000
and at 2,000, the paper's learner, each run scored by its chosen policy's test CFR at K = 10.

The paper (its results section, on the training tables): "all strategies except VDBE perform better with the
smaller buffer". THE RULE, stated before the buffer-2,000 runs were read:
- the claim's main part, on the pairs of every strategy but VDBE: supported when the one-sided Wilcoxon
  signed-rank test of 1,000 against 2,000 gives p < 0.05 and the interval of P(1,000 > 2,000), stratified by
  strategy, lies above 0.5; a lean when only its point is above 0.5; contradicted when the interval lies below
  0.5; can't tell otherwise;
- its exception, VDBE better with 2,000, by the same rule on VDBE's pairs the other way round. Three pairs give
  no one-sided p below 1/8, so it can lean at most; the page says so;
- the same tests over all pairs, and per strategy each seed's two readings side by side.
Time to drive is paired the same way; a run that did not drive by its budget counts as slower than every run
that did (it ranks past the largest budget), and the page says how many such runs there are.

The buffer's fill, from each run's own counters (summary.json replay_fill, replay/buffer_fill.py): the
episodes it stored in all, when if ever its store first held replay.capacity episodes, and the share of the
steps served (in all, and after the fill) and of those held at the end that were acted without trained weights.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from common.analysis.across_seeds import NO_IMPROVEMENT, SIGNIFICANCE
from common.analysis.intervals import Bootstrap
from common.analysis.paired import paired_improvement_estimate, signed_rank_p
from common.analysis.plotting import finish_figure, pyplot
from common.exploration.names import STRATEGIES

if TYPE_CHECKING:
    from deploy.studies.grid_report import GridRun

SMALL, LARGE = 1000, 2000
EXCEPTION = "vdbe"  # the paper's one strategy better with the larger buffer


@dataclass(frozen=True)
class BufferPair:
    strategy: str
    seed: int
    small: float | None  # at buffer 1,000; None: not reached (a run that never drove)
    large: float | None  # at buffer 2,000

    def ranked(self, past: float) -> tuple[float, float]:
        """Both values, one not reached ranked at `past` (beyond every value reached)."""
        return (past if self.small is None else self.small), (past if self.large is None else self.large)


@dataclass(frozen=True)
class PairedReading:
    what: str
    pairs: int
    p_value: float  # one-sided, first side above the second
    improvement: float  # P(first > second)
    low: float
    high: float

    @property
    def reading(self) -> str:
        if self.p_value < SIGNIFICANCE and self.low > NO_IMPROVEMENT:
            return "supported"
        if self.high < NO_IMPROVEMENT:
            return "contradicted"
        return "a lean" if self.improvement > NO_IMPROVEMENT else "can't tell"


def buffer_pairs(runs: Sequence[GridRun], score) -> list[BufferPair]:
    """Each strategy and seed that has a run of the paper's learner at both buffers, scored by score(run)."""
    by_name = {(item.run.strategy, item.run.seed, item.run.capacity): item for item in runs
               if item.run.options == "paper"}
    pairs = []
    for (strategy, seed, capacity), item in sorted(by_name.items(), key=lambda kv: (STRATEGIES.index(kv[0][0]),
                                                                                     kv[0][1], kv[0][2])):
        other = by_name.get((strategy, seed, LARGE))
        if capacity == SMALL and other is not None:
            pairs.append(BufferPair(strategy, seed, score(item), score(other)))
    return pairs


def chosen_test_cfr(item: GridRun) -> float:
    return float(item.greedy_test["cfr"])


def paired_reading(pairs: Sequence[BufferPair], what: str, bootstrap: Bootstrap, larger_better: bool = True,
                   small_first: bool = True, past: float = math.inf) -> PairedReading | None:
    """The one-sided test that the first side (1,000, or 2,000 where not small_first) beats the other; where a
    smaller value is better (updates to drive) both sides are negated, a value not reached ranked at `past`.
    None without pairs."""
    if not pairs:
        return None
    sign = 1.0 if larger_better else -1.0
    values = np.asarray([p.ranked(past) for p in pairs], dtype=float)
    small, large = sign * values[:, 0], sign * values[:, 1]
    first, second = (small, large) if small_first else (large, small)
    found = paired_improvement_estimate(first, second, [p.strategy for p in pairs], bootstrap)
    return PairedReading(what, len(pairs), signed_rank_p(first, second, "greater"), found.point,
                         found.interval.low, found.interval.high)


def claim_readings(cfr_pairs: Sequence[BufferPair], drive_pairs: Sequence[BufferPair], bootstrap: Bootstrap,
                   past: float) -> list[PairedReading]:
    """The claim's main part, its exception, and both measures over all pairs."""
    main = [p for p in cfr_pairs if p.strategy != EXCEPTION]
    exception = [p for p in cfr_pairs if p.strategy == EXCEPTION]
    readings = [paired_reading(main, "test CFR, every strategy but VDBE: 1,000 > 2,000", bootstrap),
                paired_reading(exception, "test CFR, VDBE: 2,000 > 1,000", bootstrap, small_first=False),
                paired_reading(cfr_pairs, "test CFR, all pairs: 1,000 > 2,000", bootstrap),
                paired_reading(drive_pairs, "updates to drive, all pairs: 1,000 drives sooner", bootstrap,
                               larger_better=False, past=past)]
    return [reading for reading in readings if reading is not None]


# --- the buffer's fill -----------------------------------------------------------------------------------------

def fill_row(item: GridRun) -> dict:
    """The run's buffer as its counters say; fields it did not count are None."""
    try:
        summary = json.loads(item.run.layout.summary.read_text())
    except (OSError, ValueError):
        summary = {}
    fill = summary.get("replay_fill") if isinstance(summary, dict) else None
    if not isinstance(fill, dict) or not all(isinstance(value, int) and value >= 0 for value in fill.values()):
        fill = None  # absent (a run before the counters) or malformed: not counted
    total = summary.get("replay_episodes_total") if isinstance(summary, dict) else None
    row = {"run": item.run.name, "capacity": item.run.capacity,
           "episodes_total": total if isinstance(total, int) else None,
           "counted": fill is not None, "full_at_env_steps": None, "full_at_batches": None,
           "served_random_share": None, "served_random_share_after_full": None, "sampled_batches": None}
    if fill is None:
        return row
    full = int(fill.get("full_at_env_steps") or 0)
    row.update(full_at_env_steps=full or None, full_at_batches=int(fill.get("full_at_batches") or 0) if full else None,
               served_random_share=_share(fill, "sampled_random_steps", "sampled_steps"),
               served_random_share_after_full=_share(fill, "sampled_random_steps_after_full",
                                                     "sampled_steps_after_full") if full else None,
               sampled_batches=fill.get("sampled_batches"))
    return row


def _share(fill: dict, part: str, whole: str) -> float | None:
    total = fill.get(whole) or 0
    return float(fill.get(part) or 0) / total if total else None


def fill_lines(runs: Sequence[GridRun]) -> list[str]:
    lines = ["| Run | Buffer | Episodes stored in all | Full at (env steps; batches) | Random-phase share of the "
             "steps served (after the fill) | Batches counted |", "|---|---:|---:|---|---|---:|"]
    for item in runs:
        row = fill_row(item)
        total = "–" if row["episodes_total"] is None else f"{row['episodes_total']:,d}"
        if not row["counted"]:
            lines.append(f"| {row['run']} | {row['capacity']:,d} | {total} | not counted (the run predates the "
                         "counters) | – | – |")
            continue
        full = (f"{row['full_at_env_steps']:,d}; {row['full_at_batches']:,d}" if row["full_at_env_steps"]
                else "never")
        lines.append(f"| {row['run']} | {row['capacity']:,d} | {total} | {full} | "
                     f"{_percent(row['served_random_share'])} ({_percent(row['served_random_share_after_full'])}) | "
                     f"{row['sampled_batches']:,d} |")
    return lines


def _percent(value: float | None) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{100 * value:.1f}%"


# --- the page and the figure -----------------------------------------------------------------------------------

def buffer_lines(runs: Sequence[GridRun], drive_updates, bootstrap: Bootstrap) -> list[str]:
    """The report's section on the buffer: the pairs by seed, the claim by the rule, and the fill."""
    cfr = buffer_pairs(runs, chosen_test_cfr)
    drive = buffer_pairs(runs, drive_updates)
    past = 1.0 + max((item.run.trained_updates or 0 for item in runs), default=0)
    lines = [__doc__.split("\n\n")[1].replace("\n", " "), "",
             "At 13% of the paper's budget the random phase alone fills 1,000 episodes, and the two buffers differ "
             "mostly in how much of the learner's diet it stays (docs/results/buffer-fill.md): read a gap with that.",
             ""]
    if not cfr:
        return lines + ["No strategy and seed has runs at both buffers yet.", "", *fill_lines(runs)]
    lines += ["| Strategy | Seed | Test CFR at 1,000 | at 2,000 | Updates to drive at 1,000 | at 2,000 |",
              "|---|---:|---:|---:|---:|---:|"]
    for pair, drives in zip(cfr, drive):
        lines.append(f"| {pair.strategy} | {pair.seed} | {_percent(pair.small)} | {_percent(pair.large)} | "
                     f"{_drive(drives.small)} | {_drive(drives.large)} |")
    lines += ["", "| Reading | Pairs | One-sided Wilcoxon p | P(first > second) [CI] | By the rule |",
              "|---|---:|---:|---:|---|"]
    for found in claim_readings(cfr, drive, bootstrap, past):
        lines.append(f"| {found.what} | {found.pairs} | {found.p_value:.4f} | {found.improvement:.2f} "
                     f"[{found.low:.2f}, {found.high:.2f}] | {found.reading} |")
    never = sum(value is None for p in drive for value in (p.small, p.large))
    lines += ["", f"Runs of these pairs that never drove, ranked past every budget ({past:,.0f} updates): {never}.",
              "", *fill_lines(runs)]
    return lines


def _drive(value: float | None) -> str:
    return "not reached" if value is None else f"{int(value):,d}"


def plot_buffer_pairs(pairs: Sequence[BufferPair], path: Path) -> None:
    """Each strategy's test CFR at 1,000 and 2,000 as two dots joined by a line, one line per seed."""
    plt = pyplot()
    figure, ax = plt.subplots(figsize=(10, 4.5), dpi=90)
    names = [name for name in STRATEGIES if any(p.strategy == name for p in pairs)]
    for index, name in enumerate(names):
        for pair in (p for p in pairs if p.strategy == name):
            ax.plot([index - 0.15, index + 0.15], [100 * pair.small, 100 * pair.large], marker="o", color="C0",
                    alpha=0.7)
    ax.set_xticks(range(len(names)), names, rotation=20)
    ax.set(ylabel="chosen policy's test CFR (%)")
    finish_figure(plt, figure, [ax], path, "buffer 1,000 (left dot) against 2,000 (right dot), a line per seed")
