"""Which differences between the comparison's rows its intervals support.

For two pooled rows of the comparison (two strategies on one start set and
replay capacity, or one strategy at two capacities) the difference of a
statistic, first row minus second, with the percentile interval of the
differences of bootstrap replicates. Each row is redrawn as in the tables
(common/analysis/intervals.py: its runs whole, then each run's trials within
each start), and the two rows independently of each other, because their runs
are separate trainings; a pairing of trials would narrow the interval by the
shared evaluation seeds, which is not the question asked. A difference is
*supported* when its interval leaves out 0.

With one run per row the interval shows only how the trials of two policies
vary, not how another training run of each strategy would; with two or three
seeds a run-level bootstrap has few distinct outcomes and runs narrow. Read
"supported" over a few seeds as a guide, and "not supported" as "these runs
cannot tell".

So each difference also says whether its runs lie *apart*: every run of the
first row above every run of the second, each run's statistic taken on its own
episodes (or every one below). It asks the plainer question a run-level
bootstrap of two seeds answers too readily. By chance alone, with no difference
between the strategies, two runs a side lie apart one time in three, and three
a side one time in ten; with one run a side the question is not asked.
"""

from __future__ import annotations

import csv
import math
import zlib
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path
from typing import Sequence

import numpy as np

from common.analysis.across_seeds import smallest_p_value
from common.analysis.intervals import Bootstrap, Interval, bootstrap_weights, cell_statistics, percentile_interval
from deploy.studies.comparison import BASELINES, STRATEGY_NAMES, ComparisonRow

DIFFERENCES_CSV = "differences.csv"
SHOWN = ("mean_length", "iqm_length")  # the statistics results.md lists; the CSV has every one


@dataclass(frozen=True)
class Difference:
    start_set: str
    first: ComparisonRow
    second: ComparisonRow
    statistic: str  # a statistic of common.analysis.intervals.STATISTICS
    observed: float  # first minus second, on all episodes
    interval: Interval
    runs_apart: bool | None  # every run of one row beyond every run of the other; None with one run a side

    @property
    def supported(self) -> bool:
        """The interval leaves out 0 (and exists)."""
        low, high = self.interval.low, self.interval.high
        return math.isfinite(low) and math.isfinite(high) and (low > 0.0 or high < 0.0)


def row_stream(row: ComparisonRow) -> int:
    """The row's own random stream, named by what it is, so that adding rows to a report leaves the
    intervals of the others as they were."""
    return zlib.crc32(f"{row.start_set}/{row.capacity}/{row.strategy}".encode())


def row_replicates(row: ComparisonRow, bootstrap: Bootstrap) -> dict[str, np.ndarray]:
    """Every statistic of the row under `bootstrap.replicates` draws of its own random stream."""
    if row.cell is None:
        raise ValueError(f"row {row.strategy!r} has no episodes to resample")
    rng = np.random.default_rng([bootstrap.seed, row_stream(row)])
    return cell_statistics(row.cell, bootstrap_weights(row.cell.runs, row.cell.starts, bootstrap.replicates, rng))


def observed_statistics(row: ComparisonRow) -> dict[str, float]:
    weights = np.ones(len(row.cell.lengths))
    return {name: float(value) for name, value in cell_statistics(row.cell, weights).items()}


def run_statistics(row: ComparisonRow) -> dict[str, np.ndarray]:
    """Every statistic of each of the row's runs on that run's own episodes, one value per run."""
    weights = np.stack([(row.cell.runs == run).astype(np.float64) for run in np.unique(row.cell.runs)])
    return cell_statistics(row.cell, weights)


def chance_apart(first_runs: int, second_runs: int) -> float:
    """How often runs lie apart by chance alone, with no difference between the strategies: of the ways to
    order n + m exchangeable values, the 2 that put one side wholly above the other (2 n! m! / (n + m)!), each
    the smallest p-value of a one-sided exact Mann-Whitney test."""
    return 2 * smallest_p_value(first_runs, second_runs)


def chances_apart(found: Sequence[Difference]) -> str:
    """The chance of lying apart for each count of runs that the differences compare, in words."""
    counts = sorted({tuple(sorted((d.first.runs, d.second.runs))) for d in found if d.runs_apart is not None})
    return "; ".join(f"{fewer} against {more} one time in {round(1 / chance_apart(fewer, more))}"
                     for fewer, more in counts)


def lie_apart(first: np.ndarray, second: np.ndarray) -> bool | None:
    """Every value of one side beyond every value of the other (None unless each side has two or more, or
    when a run's value is missing: a NaN cannot be placed, so the question is not asked)."""
    if min(len(first), len(second)) < 2 or np.isnan(first).any() or np.isnan(second).any():
        return None
    return bool(first.min() > second.max() or first.max() < second.min())


def compared_pairs(rows: Sequence[ComparisonRow]) -> list[tuple[ComparisonRow, ComparisonRow]]:
    """Trained pooled rows: every two strategies of one start set and capacity (in the tables' order), then
    every strategy at two capacities of one start set (smaller capacity first)."""
    trained = [row for row in rows if row.pooled and row.strategy not in BASELINES]
    pairs = []
    for key in dict.fromkeys((row.start_set, row.capacity) for row in trained):
        pairs += combinations([row for row in trained if (row.start_set, row.capacity) == key], 2)
    for key in dict.fromkeys((row.start_set, row.strategy) for row in trained):
        same = sorted((row for row in trained if (row.start_set, row.strategy) == key), key=lambda row: row.capacity)
        pairs += combinations(same, 2)
    return pairs


def differences(rows: Sequence[ComparisonRow], bootstrap: Bootstrap | None = None) -> list[Difference]:
    """Every compared pair's difference in every statistic, each row drawn from a stream of its own."""
    bootstrap = bootstrap or Bootstrap()
    pairs = compared_pairs(rows)
    members = list({id(row): row for pair in pairs for row in pair}.values())
    replicates = {id(row): row_replicates(row, bootstrap) for row in members}
    observed = {id(row): observed_statistics(row) for row in members}
    per_run = {id(row): run_statistics(row) for row in members}
    found = []
    for first, second in pairs:
        for statistic in replicates[id(first)]:
            spread = replicates[id(first)][statistic] - replicates[id(second)][statistic]
            found.append(Difference(first.start_set, first, second, statistic,
                                    observed[id(first)][statistic] - observed[id(second)][statistic],
                                    percentile_interval(spread, bootstrap.confidence),
                                    lie_apart(per_run[id(first)][statistic], per_run[id(second)][statistic])))
    return found


def differences_markdown(found: Sequence[Difference], confidence: float = 0.95) -> str:
    """One table per start set: each pair's difference in mean and IQM length, whether it is supported, and
    whether the runs lie apart."""
    level = f"{100 * confidence:g}% CI"
    header = ["First", "Second", "Runs", f"Mean length, first - second [{level}]", f"IQM, first - second [{level}]",
              "Supported", "Runs apart"]
    sections = []
    for start_set in dict.fromkeys(difference.start_set for difference in found):
        by_pair: dict[tuple[int, int], dict[str, Difference]] = {}
        for difference in found:
            if difference.start_set == start_set and difference.statistic in SHOWN:
                by_pair.setdefault((id(difference.first), id(difference.second)), {})[difference.statistic] = difference
        lines = [f"### Differences, {start_set} set", "", "| " + " | ".join(header) + " |",
                 "|---|---|---:|---:|---:|---|---|"]
        for pair in by_pair.values():
            mean, iqm = pair["mean_length"], pair["iqm_length"]
            lines.append("| " + " | ".join([_label(mean.first), _label(mean.second),
                                             f"{mean.first.runs} vs {mean.second.runs}", _signed(mean),
                                             _signed(iqm), _verdict(mean, iqm), _apart(mean, iqm)]) + " |")
        sections.append("\n".join(lines))
    return "\n\n".join(sections) + "\n" if sections else ""


def write_differences_csv(found: Sequence[Difference], path: Path) -> None:
    fields = ["start_set", "first_strategy", "first_capacity", "first_runs", "second_strategy", "second_capacity",
              "second_runs", "statistic", "difference", "ci_low", "ci_high", "supported", "runs_apart"]
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(fields)
        for d in found:
            writer.writerow([d.start_set, d.first.strategy, d.first.capacity, d.first.runs, d.second.strategy,
                             d.second.capacity, d.second.runs, d.statistic, repr(d.observed), repr(d.interval.low),
                             repr(d.interval.high), int(d.supported), "" if d.runs_apart is None else int(d.runs_apart)])


def _label(row: ComparisonRow) -> str:
    return f"{STRATEGY_NAMES.get(row.strategy, row.strategy)}, {row.capacity:,d}"


def _signed(difference: Difference) -> str:
    return (f"{difference.observed:+,.2f} [{difference.interval.low:+,.2f}, {difference.interval.high:+,.2f}]"
            if math.isfinite(difference.observed) else "–")


def _holding(mean: Difference, iqm: Difference, holds) -> list[str]:
    """Which of the two statistics `holds`, by name."""
    return [name for name, difference in (("mean", mean), ("IQM", iqm)) if holds(difference)]


def _verdict(mean: Difference, iqm: Difference) -> str:
    said = _holding(mean, iqm, lambda difference: difference.supported)
    trials_only = " (trials only)" if said and min(mean.first.runs, mean.second.runs) == 1 else ""
    return " and ".join(said) + trials_only if said else "no"


def _apart(mean: Difference, iqm: Difference) -> str:
    if mean.runs_apart is None:
        return "–"
    said = _holding(mean, iqm, lambda difference: difference.runs_apart)
    return " and ".join(said) if said else "no"
