"""The paper's tables 3-6 across runs: evaluations read back, pooled per strategy and replay capacity.

Each run's ``episodes.csv`` (written by ``evaluate``) is read back into
EvaluationEpisode records, and the greedy episodes of all runs that share a
strategy and a replay capacity (the seeds of one grid cell) are pooled into one
row by ``evaluation_stats.summarise``, so a row weighs every episode once. One
table per start set and capacity: Strategy | Runs | Episodes | Average |
Standard Deviation | Min | CFR | Reward/step | the last reward bin's share.
The random policy does not depend on the training, and every evaluation with
the same seed runs the same random trials, so its row is taken once, from the
first run that has it, and shown in every table of its start set.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from actor.evaluation_report import EPISODES_CSV, bin_labels
from actor.evaluation_stats import EvaluationEpisode, SetSummary, summarise
from common.config import STRATEGIES

STRATEGY_NAMES = {
    "constant": "Constant ε-greedy",
    "decreasing": "Decreasing ε-greedy",
    "vdbe": "VDBE",
    "bmc": "BMC",
    "softmax": "Softmax",
    "max_boltzmann": "MBE",
    "vdbe_softmax": "VDBE-Softmax",
    "random": "Random policy",
}
RANDOM = "random"
BIN_PREFIX = "steps_"
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


@dataclass(frozen=True)
class ComparisonRow:
    strategy: str  # a strategy of common.config.STRATEGIES, or "random"
    capacity: int
    runs: int  # evaluations pooled in the row
    summary: SetSummary

    @property
    def start_set(self) -> str:
        return self.summary.start_set


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
                             actions_digest=row["actions_digest"])


# --- pooling ------------------------------------------------------------------------------------------------

def comparison_rows(runs: Sequence[EvaluatedRun]) -> tuple[list[ComparisonRow], list[float]]:
    """Rows by start set, capacity, then strategy in common.config order with the random row last; and the edges."""
    greedy: dict[tuple[str, int, str], list[EvaluationEpisode]] = {}
    pooled_runs: dict[tuple[str, int, str], int] = {}
    random_rows: dict[str, list[EvaluationEpisode]] = {}
    edges: list[float] | None = None
    for run in runs:
        episodes, run_edges = read_episodes_csv(run.evaluation_dir / EPISODES_CSV)
        if edges is not None and run_edges != edges:
            raise ComparisonError(f"{run.evaluation_dir}: reward bins {run_edges} differ from the others' {edges}")
        edges = run_edges
        by_set = _by_policy_and_set(episodes)
        for (policy, start_set), group in by_set.items():
            if policy == "greedy":
                key = (start_set, run.capacity, run.strategy)
                greedy.setdefault(key, []).extend(group)
                pooled_runs[key] = pooled_runs.get(key, 0) + 1
            elif policy == RANDOM:
                random_rows.setdefault(start_set, group)
    if edges is None:
        raise ComparisonError("no evaluated runs to compare")
    rows = []
    for start_set, capacity in sorted({(key[0], key[1]) for key in greedy}, key=_set_then_capacity):
        for strategy in sorted({key[2] for key in greedy if key[:2] == (start_set, capacity)}, key=_strategy_rank):
            key = (start_set, capacity, strategy)
            rows.append(ComparisonRow(strategy, capacity, pooled_runs[key], summarise(greedy[key])))
        if start_set in random_rows:
            rows.append(ComparisonRow(RANDOM, capacity, 1, summarise(random_rows[start_set])))
    return rows, edges


def _by_policy_and_set(episodes: Sequence[EvaluationEpisode]) -> dict[tuple[str, str], list[EvaluationEpisode]]:
    groups: dict[tuple[str, str], list[EvaluationEpisode]] = {}
    for episode in episodes:
        groups.setdefault((episode.policy, episode.start_set), []).append(episode)
    return groups


def _set_then_capacity(key: tuple[str, int]) -> tuple[int, int]:
    start_set, capacity = key
    return (0 if start_set == "train" else 1, capacity)  # the paper's order: training set first


def _strategy_rank(strategy: str) -> int:
    return STRATEGIES.index(strategy) if strategy in STRATEGIES else len(STRATEGIES)


# --- output ----------------------------------------------------------------------------------------------------

def comparison_markdown(rows: Sequence[ComparisonRow], edges: Sequence[float]) -> str:
    """One table per start set and capacity, as the paper's tables 3-6 with three more columns."""
    last_bin = bin_labels(edges)[-1]
    header = ["Strategy", "Runs", "Episodes", "Average", "Standard Deviation", "Min", "CFR", "Reward/step",
              f"r in {last_bin}"]
    sections: list[str] = []
    for start_set, capacity in dict.fromkeys((row.start_set, row.capacity) for row in rows):
        lines = [f"### {start_set.capitalize()} set, replay capacity {capacity:,d} episodes", "",
                 "| " + " | ".join(header) + " |", "|" + "|".join(["---"] + ["---:"] * (len(header) - 1)) + "|"]
        for row in rows:
            if (row.start_set, row.capacity) == (start_set, capacity):
                s = row.summary
                cells = [STRATEGY_NAMES.get(row.strategy, row.strategy), str(row.runs), str(s.episodes),
                         f"{s.mean_length:,.2f}", f"{s.std_length:,.2f}", f"{s.min_length:,d}", _percent(s.cfr),
                         f"{s.mean_reward_per_step:.3f}", _percent(s.reward_shares[-1])]
                lines.append("| " + " | ".join(cells) + " |")
        sections.append("\n".join(lines))
    return "\n\n".join(sections) + "\n"


def write_comparison_csv(rows: Sequence[ComparisonRow], edges: Sequence[float], path: Path) -> None:
    """Every row at full precision, all reward-bin shares included."""
    shares = [f"share_{low:g}_{high:g}" for low, high in zip(edges, edges[1:])]
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["start_set", "capacity", "strategy", "runs", "episodes", "mean_length", "std_length",
                         "min_length", "cfr", "mean_reward_per_step", *shares])
        for row in rows:
            s = row.summary
            writer.writerow([row.start_set, row.capacity, row.strategy, row.runs, s.episodes, s.mean_length,
                             s.std_length, s.min_length, s.cfr, s.mean_reward_per_step, *s.reward_shares])


def _percent(share: float) -> str:
    return f"{100 * share:.2f}%"
