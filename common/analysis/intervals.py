"""Confidence intervals for the evaluation tables: a two-stage stratified bootstrap over runs and trials.

An evaluation cell (one strategy, buffer and start set) holds episodes indexed
by the training run that made the policy (its seed), the start pose they drove
from, and the trial. The runs are the independent replicates of the
experiment, and one run is evaluated on every start, so a good run is good at
all its starts. The starts are fixed by the protocol: strata, not samples.
One bootstrap replicate therefore

1. draws as many runs as there are, uniformly with replacement, jointly for
   all starts (a run is resampled whole, as a new training run would be);
2. for every drawn run and every start, draws that run's trials from that
   start again, uniformly with replacement and as many as it has;

and computes the statistic on the pooled replicate. With one run (``evaluate``
on one checkpoint) step 1 is trivial: the interval then shows only how much
the trials of that policy vary, not how much another training run would
differ. With a handful of runs the bootstrap's spread is a little narrower
than the truth (it has n - 1 rather than n degrees of freedom): read an
interval over three seeds as a guide, not a test.

A replicate is a matrix of counts (how often each episode was drawn), so every
statistic is a weighted one: shares, means, the pooled reward per step (sum of
returns over sum of steps) and the interquartile mean. Intervals are
percentile intervals of ``replicates`` replicates at level ``confidence``.
rliable's StratifiedBootstrap was considered and not used: it redraws runs
independently for every task (here: start), which treats the starts of one
run as if they came from different runs, and it has no second stage for the
trials.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Hashable, Sequence

import numpy as np

from common.config import Config

STATISTICS = ("mean_length", "iqm_length", "cfr", "reward_per_step", "progress_m", "streets", "junctions")


@dataclass(frozen=True)
class Bootstrap:
    """How intervals are computed; the defaults are evaluation.bootstrap_replicates and evaluation.confidence."""

    replicates: int = 2000
    confidence: float = 0.95
    seed: int = 0

    def __post_init__(self) -> None:
        if self.replicates < 1:
            raise ValueError(f"bootstrap replicates must be >= 1, got {self.replicates}")
        if not 0.0 < self.confidence < 1.0:
            raise ValueError(f"confidence must lie in (0, 1), got {self.confidence}")


def bootstrap_of(config: Config) -> Bootstrap:
    """The intervals' settings; the bootstrap draws from evaluation.seed, so a table is reproducible."""
    evaluation = config.evaluation
    return Bootstrap(evaluation.bootstrap_replicates, evaluation.confidence, evaluation.seed)


@dataclass(frozen=True)
class Interval:
    low: float
    high: float

    @property
    def width(self) -> float:
        return self.high - self.low


@dataclass(frozen=True)
class Cell:
    """The episodes of one table row as arrays, with the run and the start each came from."""

    runs: np.ndarray  # one label per episode: the training run (seed) whose policy drove it
    starts: np.ndarray  # one label per episode: its start pose
    lengths: np.ndarray  # float64 steps
    capped: np.ndarray  # float64 1.0 where the episode reached the step cap (collision-free)
    returns: np.ndarray  # float64 sum of step rewards
    progress_m: np.ndarray  # float64 metres along the road; NaN where the simulator did not report it
    streets: np.ndarray  # float64 distinct streets visited; NaN where the simulator did not report them
    junctions: np.ndarray  # float64 distinct junctions visited; NaN likewise

    @classmethod
    def of(cls, runs: Sequence[Hashable], starts: Sequence[Hashable], lengths: Sequence[float],
           capped: Sequence[bool], returns: Sequence[float], progress_m: Sequence[float],
           streets: Sequence[float] | None = None, junctions: Sequence[float] | None = None) -> "Cell":
        """streets, junctions: NaN for every episode when not given."""
        unknown = [math.nan] * len(lengths)
        arrays = [np.asarray(values, dtype=np.float64) for values in
                  (lengths, capped, returns, progress_m, unknown if streets is None else streets,
                   unknown if junctions is None else junctions)]
        cell = cls(_codes(runs), _codes(starts), *arrays)
        sizes = {len(array) for array in (cell.runs, cell.starts, *arrays)}
        if len(sizes) != 1 or not sizes.pop():
            raise ValueError("a cell needs the same positive number of runs, starts, lengths, flags, returns, "
                             "progress, streets, junctions")
        if (cell.lengths <= 0).any():
            raise ValueError("every episode must have at least one step")
        return cell


def _codes(labels: Sequence[Hashable]) -> np.ndarray:
    """Labels as integer codes 0..k-1 in order of first appearance."""
    index: dict[Hashable, int] = {}
    return np.array([index.setdefault(label, len(index)) for label in labels], dtype=np.int64)


def bootstrap_weights(runs: np.ndarray, starts: np.ndarray, replicates: int, rng: np.random.Generator) -> np.ndarray:
    """(replicates, episodes) counts: runs drawn jointly, then each drawn run's trials within each start.

    Drawing a run m times and its n trials at a start n times each time draws m * n
    trials from that start's n, which is one multinomial per (run, start).
    """
    runs, starts = np.asarray(runs), np.asarray(starts)
    run_ids = np.unique(runs)
    run_draws = rng.multinomial(len(run_ids), np.full(len(run_ids), 1.0 / len(run_ids)), size=replicates)
    weights = np.zeros((replicates, len(runs)))
    for column, run in enumerate(run_ids):
        for start in np.unique(starts[runs == run]):
            members = np.flatnonzero((runs == run) & (starts == start))
            draws = run_draws[:, column] * len(members)
            weights[:, members] = rng.multinomial(draws, np.full(len(members), 1.0 / len(members)))
    return weights


def weighted_iqm(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Interquartile mean: the mean of the middle half of the weight, boundary values counted in part.

    values (N,), weights (N,) or (B, N); one IQM per row. Unweighted and N a multiple
    of 4, it is the mean of the middle N / 2 sorted values (scipy's trim_mean(x, 0.25)).
    """
    values = np.asarray(values, dtype=np.float64)
    order = np.argsort(values, kind="stable")
    sorted_values = values[order]
    sorted_weights = np.asarray(weights, dtype=np.float64)[..., order]
    upper = np.cumsum(sorted_weights, axis=-1)
    lower = upper - sorted_weights
    total = upper[..., -1:]
    overlap = np.clip(np.minimum(upper, 0.75 * total) - np.maximum(lower, 0.25 * total), 0.0, None)
    return (overlap * sorted_values).sum(axis=-1) / (0.5 * total[..., 0])


def cell_statistics(cell: Cell, weights: np.ndarray) -> dict[str, np.ndarray]:
    """Every statistic of STATISTICS under weights (N,) or (B, N)."""
    total = weights.sum(axis=-1)
    with np.errstate(invalid="ignore"):  # NaN progress or coverage stays NaN
        progress, streets, junctions = (weights @ values / total
                                        for values in (cell.progress_m, cell.streets, cell.junctions))
    return {
        "mean_length": weights @ cell.lengths / total,
        "iqm_length": weighted_iqm(cell.lengths, weights),
        "cfr": weights @ cell.capped / total,
        "reward_per_step": (weights @ cell.returns) / (weights @ cell.lengths),
        "progress_m": progress,
        "streets": streets,
        "junctions": junctions,
    }


def percentile_interval(replicates: np.ndarray, confidence: float) -> Interval:
    """The central `confidence` share of the replicates (inverted empirical CDF, so ends are replicate values)."""
    replicates = np.asarray(replicates, dtype=np.float64)
    if replicates.size == 0 or not np.isfinite(replicates).all():
        return Interval(math.nan, math.nan)
    tail = (1.0 - confidence) / 2.0
    low, high = np.quantile(replicates, [tail, 1.0 - tail], method="inverted_cdf")
    return Interval(float(low), float(high))


def cell_intervals(cell: Cell, bootstrap: Bootstrap) -> dict[str, Interval]:
    """One percentile interval per statistic of STATISTICS."""
    weights = bootstrap_weights(cell.runs, cell.starts, bootstrap.replicates, np.random.default_rng(bootstrap.seed))
    return {name: percentile_interval(values, bootstrap.confidence)
            for name, values in cell_statistics(cell, weights).items()}


def profile_band(lengths: np.ndarray, weights: np.ndarray, thresholds: np.ndarray, confidence: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Share of episodes longer than each threshold: observed, and the band's low and high ends.

    weights: (B, N) bootstrap counts of the same episodes.
    """
    longer = (np.asarray(lengths, dtype=np.float64)[:, None] > np.asarray(thresholds)[None, :]).astype(np.float64)
    observed = longer.mean(axis=0)
    shares = weights @ longer / weights.sum(axis=1, keepdims=True)
    tail = (1.0 - confidence) / 2.0
    low, high = np.quantile(shares, [tail, 1.0 - tail], axis=0, method="inverted_cdf")
    return observed, low, high
