"""The paper's tables 3-6 across runs: evaluations read back, pooled per strategy and replay capacity.

Each run's ``episodes.csv`` (written by ``evaluate``) is read back into
EvaluationEpisode records, and the greedy episodes of all runs that share a
strategy and a replay capacity (the seeds of one grid cell) are pooled into one
row by ``common.analysis.stats.summarise``, so a row weighs every episode once; its
intervals resample the runs whole, then each run's trials within each start
(common/analysis/intervals.py). Each run also gets a row of its own. One
table per start set and capacity: Strategy | Seeds | Updates (of every run) |
Episodes | Average | IQM | Standard Deviation | Min | CFR | Ends (collision /
off-road / stalled) | Progress | Reward/step | the last reward bin's share;
then the per-run rows.
The baselines do not depend on the training: the random policy and, where an
evaluation ran it, the privileged map-reading driver. Every evaluation with the
same seed runs the same trials of them, so each one's row is taken once, from
the first run that has it, and shown in every table of its start set.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from common.analysis.intervals import Bootstrap, Cell
from common.analysis.stats import EvaluationEpisode, SetSummary, episode_cell, summarise
from common.analysis.tables import EPISODES_CSV, bin_labels, summary_columns, with_interval
from common.exploration.names import DISPLAY_NAMES, strategy_rank

RANDOM = "random"
PRIVILEGED = "privileged"
BASELINES = (RANDOM, PRIVILEGED)  # evaluate's policies that need no training, in the tables' order
STRATEGY_NAMES = {**DISPLAY_NAMES, RANDOM: "Random policy", PRIVILEGED: "Privileged driver"}
BIN_PREFIX = "steps_"
OPTIONAL_EPISODE_COLUMNS = ("progress_m", "streets", "junctions", "end_x", "end_y", "end_heading")  # NaN where absent
RESULTS_CSV = "results.csv"
RESULTS_MD = "results.md"


class ComparisonError(ValueError):
    """The evaluations cannot be read or compared."""


@dataclass(frozen=True)
class EvaluatedRun:
    """One trained and evaluated run of the grid."""

    strategy: str
    capacity: int
    evaluation_dir: Path  # holds evaluate's episodes.csv
    seed: int = 0  # run.seed of its training
    updates: int | None = None  # the learner's updates when its checkpoint was evaluated, if known


@dataclass(frozen=True)
class ComparisonRow:
    strategy: str  # a strategy of common.exploration.names.STRATEGIES, or a baseline (BASELINES)
    capacity: int
    runs: int  # evaluations pooled in the row
    summary: SetSummary
    seed: int | None = None  # None: the runs of every seed pooled; else this seed's run alone
    seeds: tuple[int, ...] = ()  # the seeds of the runs in the row
    updates: tuple[int | None, ...] = ()  # every run's updates, in the order of seeds
    cell: Cell | None = None  # the row's episodes as the bootstrap sees them (for the performance profile)

    @property
    def start_set(self) -> str:
        return self.summary.start_set

    @property
    def pooled(self) -> bool:
        return self.seed is None


# --- reading evaluations back ---------------------------------------------------------------------------

def read_episodes_csv(path: Path) -> tuple[list[EvaluationEpisode], list[float]]:
    """The episodes of an evaluate episodes.csv and the reward-bin edges named in its header."""
    try:
        with path.open(newline="") as handle:
            rows = list(csv.DictReader(handle))
    except OSError as error:
        raise ComparisonError(f"{path}: cannot read ({error.strerror})") from None
    if not rows:
        raise ComparisonError(f"{path}: no episodes")
    bin_columns = [name for name in rows[0] if name.startswith(BIN_PREFIX)]
    try:
        edges = _edges_of(bin_columns)
        episodes = [_episode_of(row, bin_columns) for row in rows]
    except (KeyError, ValueError, TypeError) as error:
        raise ComparisonError(f"{path}: not an episodes.csv of evaluate ({type(error).__name__}: {error})") from None
    return episodes, edges


def _edges_of(bin_columns: list[str]) -> list[float]:
    """'steps_0_0.25', 'steps_0.25_0.5', ... -> [0, 0.25, 0.5, ...]."""
    pairs = [tuple(float(part) for part in name[len(BIN_PREFIX):].split("_")) for name in bin_columns]
    if not pairs or any(low != high for (_, low), (high, _) in zip(pairs, pairs[1:])):
        raise ValueError(f"reward-bin columns {bin_columns} are not consecutive bins")
    return [pairs[0][0], *(high for _, high in pairs)]


def _episode_of(row: dict[str, str], bin_columns: list[str]) -> EvaluationEpisode:
    return EvaluationEpisode(policy=row["policy"], start_set=row["start_set"], start_index=int(row["start_index"]),
                             trial=int(row["trial"]), seed=int(row["seed"]), length=int(row["length"]),
                             end=row["end"], episode_return=float(row["episode_return"]),
                             reward_bin_counts=tuple(int(row[name]) for name in bin_columns),
                             actions_digest=row["actions_digest"],  # older files lack the columns below
                             **{name: float(row.get(name) or math.nan) for name in OPTIONAL_EPISODE_COLUMNS},
                             end_place=row.get("end_place") or "", hit=row.get("hit") or "")


# --- pooling ------------------------------------------------------------------------------------------------

def comparison_rows(runs: Sequence[EvaluatedRun], bootstrap: Bootstrap | None = None
                    ) -> tuple[list[ComparisonRow], list[float]]:
    """Rows by start set, capacity, then strategy in common.exploration.names order, each pooled row followed by one
    row per run (by seed, even when there is only one), the baselines' rows last; and the edges."""
    greedy: dict[tuple[str, int, str], list[tuple[EvaluatedRun, list[EvaluationEpisode]]]] = {}
    baseline_rows: dict[tuple[str, str], list[EvaluationEpisode]] = {}
    edges: list[float] | None = None
    for run in runs:
        episodes, run_edges = read_episodes_csv(run.evaluation_dir / EPISODES_CSV)
        if edges is not None and run_edges != edges:
            raise ComparisonError(f"{run.evaluation_dir}: reward bins {run_edges} differ from the others' {edges}")
        edges = run_edges
        for (policy, start_set), group in _by_policy_and_set(episodes).items():
            if policy == "greedy":
                greedy.setdefault((start_set, run.capacity, run.strategy), []).append((run, group))
            elif policy in BASELINES:
                baseline_rows.setdefault((policy, start_set), group)
    if edges is None:
        raise ComparisonError("no evaluated runs to compare")
    rows = []
    for start_set, capacity in sorted({(key[0], key[1]) for key in greedy}, key=_set_then_capacity):
        for strategy in sorted({key[2] for key in greedy if key[:2] == (start_set, capacity)}, key=strategy_rank):
            members = sorted(greedy[(start_set, capacity, strategy)], key=lambda member: member[0].seed)
            rows.append(_row(strategy, capacity, members, None, bootstrap))
            rows += [_row(strategy, capacity, [member], member[0].seed, bootstrap) for member in members]
        for baseline in BASELINES:
            if (baseline, start_set) in baseline_rows:
                rows.append(_row(baseline, capacity, [(None, baseline_rows[(baseline, start_set)])], None, bootstrap))
    return rows, edges


def _row(strategy: str, capacity: int, members: list[tuple[EvaluatedRun | None, list[EvaluationEpisode]]],
         seed: int | None, bootstrap: Bootstrap | None) -> ComparisonRow:
    """One row over the episodes of `members` (run, its episodes); each run is one stratum of the bootstrap."""
    episodes = [episode for _, group in members for episode in group]
    labels = [number for number, (_, group) in enumerate(members) for _ in group]
    trained = [run for run, _ in members if run is not None]
    return ComparisonRow(strategy, capacity, len(members), summarise(episodes, labels, bootstrap), seed,
                         tuple(run.seed for run in trained), tuple(run.updates for run in trained),
                         episode_cell(episodes, labels))


def _by_policy_and_set(episodes: Sequence[EvaluationEpisode]) -> dict[tuple[str, str], list[EvaluationEpisode]]:
    groups: dict[tuple[str, str], list[EvaluationEpisode]] = {}
    for episode in episodes:
        groups.setdefault((episode.policy, episode.start_set), []).append(episode)
    return groups


def _set_then_capacity(key: tuple[str, int]) -> tuple[int, int]:
    start_set, capacity = key
    return (0 if start_set == "train" else 1, capacity)  # the paper's order: training set first


# --- output ----------------------------------------------------------------------------------------------------

def comparison_markdown(rows: Sequence[ComparisonRow], edges: Sequence[float], confidence: float = 0.95) -> str:
    """One table per start set and capacity, as the paper's tables 3-6 with intervals and more columns,
    then the table of every run on its own."""
    last_bin = bin_labels(edges)[-1]
    level = f"{100 * confidence:g}% CI"
    header = ["Strategy", "Seeds", "Updates", "Episodes", f"Average [{level}]", f"IQM [{level}]", "Standard Deviation",
              "Min", f"CFR [{level}]", "Ends: collision / off-road / stalled", "Progress m", f"Reward/step [{level}]", f"r in {last_bin}"]
    per_run = ["Strategy", "Seed", "Updates", "Episodes", f"Average [{level}]", f"IQM [{level}]", f"CFR [{level}]",
               f"Reward/step [{level}]"]
    sections: list[str] = []
    for start_set, capacity in dict.fromkeys((row.start_set, row.capacity) for row in rows):
        table = [row for row in rows if (row.start_set, row.capacity) == (start_set, capacity)]
        lines = [f"### {start_set.capitalize()} set, replay capacity {capacity:,d} episodes", "", *_table_head(header)]
        for row in table:
            if row.pooled:
                s = row.summary
                lines.append(_table_line([
                    STRATEGY_NAMES.get(row.strategy, row.strategy), _seeds(row), _updates(row), str(s.episodes),
                    with_interval(s, "mean_length"), with_interval(s, "iqm_length"), f"{s.std_length:,.2f}",
                    f"{s.min_length:,d}", with_interval(s, "cfr", percent=True), _ends(s),
                    _number(s.mean_progress_m), with_interval(s, "reward_per_step", digits=3),
                    _percent(s.reward_shares[-1])]))
        singles = [row for row in table if not row.pooled]
        if any(row.runs > 1 for row in table if row.pooled):  # with one run per row they repeat the rows above
            lines += ["", "Each run on its own:", "", *_table_head(per_run)]
            for row in singles:
                s = row.summary
                lines.append(_table_line([
                    STRATEGY_NAMES.get(row.strategy, row.strategy), str(row.seed), _updates(row), str(s.episodes),
                    with_interval(s, "mean_length"), with_interval(s, "iqm_length"),
                    with_interval(s, "cfr", percent=True), with_interval(s, "reward_per_step", digits=3)]))
        sections.append("\n".join(lines))
    return "\n\n".join(sections) + "\n"


def write_comparison_csv(rows: Sequence[ComparisonRow], edges: Sequence[float], path: Path) -> None:
    """Every row, pooled (seed "all") and per run, at full precision with its intervals and reward-bin shares."""
    table = [{"start_set": row.start_set, "capacity": row.capacity, "strategy": row.strategy,
              "seed": "all" if row.pooled else row.seed, "seeds": ";".join(map(str, row.seeds)),
              "updates": ";".join("" if updates is None else str(updates) for updates in row.updates),
              **summary_columns(row.summary, edges)} for row in rows]
    with path.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(table[0]) if table else [])
        writer.writeheader()
        writer.writerows(table)


def _table_head(header: list[str]) -> list[str]:
    return [_table_line(header), "|" + "|".join(["---"] + ["---:"] * (len(header) - 1)) + "|"]


def _table_line(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def _seeds(row: ComparisonRow) -> str:
    return ", ".join(map(str, row.seeds)) if row.seeds else "–"


def _updates(row: ComparisonRow) -> str:
    """Every run's updates, so a reader sees at once whether the runs of a row trained alike."""
    return ", ".join("?" if updates is None else f"{updates:,d}" for updates in row.updates) or "–"


def _number(value: float) -> str:
    return f"{value:,.1f}" if math.isfinite(value) else "–"


def _ends(summary: SetSummary) -> str:
    shares = (summary.collision_share, summary.offroad_share, summary.stalled_share)
    return " / ".join(f"{100 * share:.0f}%" for share in shares)


def _percent(share: float) -> str:
    return f"{100 * share:.2f}%"
