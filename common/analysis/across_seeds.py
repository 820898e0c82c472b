"""Statistics across training runs (seeds): the interquartile mean, the probability of improvement, and the rule
that turns them into a reading of a claim.

Scores are a matrix, runs x tasks, per strategy (or per pool of strategies): a run is one training seed, a task
one start pose of the test set (10 of them), or a single column when a run gives one scalar. Strategies may
have different numbers of runs; the tasks must be the same. The estimates are those of Agarwal et al. (2021,
"Deep RL at the Edge of the Statistical Precipice", the rliable library), so that they compare with it
(deploy/bench/rliable_check.py, results/rliable-check.txt):

* IQM: the mean of the middle half of all run x task scores pooled, scipy's ``trim_mean(scores, 0.25)``:
  int(0.25 N) scores are cut from each end. This is not common/analysis/intervals.py's ``weighted_iqm``, which
  counts the boundary scores in part; the two agree when N is a multiple of 4 and differ otherwise (30 scores:
  trim_mean averages the middle 16 alike, weighted_iqm counts the outer two of them at half weight).
* Probability of improvement P(X > Y): on each task, the share of (run of X, run of Y) pairs in which X's score
  is above Y's, a tie counting one half (the Mann-Whitney U of X against Y over n_x n_y), averaged over tasks.
* Intervals: the stratified bootstrap of rliable. A replicate draws, for every task independently, as many runs
  as there are, uniformly with replacement; for P(X > Y) the two sides are drawn independently of each other.
  Percentile intervals (``intervals.percentile_interval``) of ``Bootstrap.replicates`` replicates at
  ``Bootstrap.confidence``, from a numpy Generator seeded with ``Bootstrap.seed``. This differs from the
  tables' bootstrap (intervals.py), which draws a run jointly for all starts; here it is kept as rliable has it
  so that the figures mean what the paper's method means. With three runs per strategy a bootstrap over runs
  has few distinct outcomes: its intervals run narrow.

The claims rule. A claim "A beats B" compares group A's runs with group B's runs, each side pooled over one or
more strategies (the paper's claim 1: Softmax, MBE, VDBE-Softmax and BMC, 12 runs, against constant and
decreasing epsilon-greedy, 6 runs). Its reading is

* "supported": the one-sided Mann-Whitney test of A's runs against B's runs (alternative "greater"; each run's
  score its mean over the tasks) gives p < SIGNIFICANCE (0.05), and the interval of P(A > B) lies wholly
  above NO_IMPROVEMENT (0.5);
* "a lean": not supported, but the point estimate of P(A > B) is above 0.5;
* "can't tell": otherwise (no difference shown, or B ahead: ``reverse_claim`` reads B against A for that,
  by the same rule with the two-sided p-value, since that direction was chosen after the fact).

The test's p-value is exact for small samples, ties included: the permutation distribution of U over every split
of the pooled runs (any sizes, one run a side too), and the normal approximation only past EXACT_ARRANGEMENTS
splits. No exact test of n runs against m can give less than 1 / C(n + m, n), the chance that
A's runs are the top n by chance alone. Three seeds against three give at best 1/20 = 0.05, which is not below
0.05: three seeds a side can never support a pairwise claim; four a side can (1/70).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np
from scipy import stats

from common.analysis.intervals import Bootstrap, Interval, percentile_interval

SIGNIFICANCE = 0.05  # a claim needs its one-sided p-value below this
NO_IMPROVEMENT = 0.5  # P(A > B) when neither side is ahead; a claim needs its interval above this
EXACT_ARRANGEMENTS = 1_000_000  # splits of the pooled runs up to which the p-value is exact
IQM_TRIM = 0.25  # the share of scores cut from each end for the interquartile mean

SUPPORTED, LEAN, CANT_TELL = "supported", "a lean", "can't tell"


@dataclass(frozen=True)
class Estimate:
    point: float
    interval: Interval


@dataclass(frozen=True)
class Claim:
    """A claim "A beats B": the test, the probability of improvement, and what they read as together."""

    a_runs: int
    b_runs: int
    p_value: float  # one-sided Mann-Whitney, A greater than B, on the runs' mean scores
    improvement: Estimate  # P(A > B) with its stratified bootstrap interval
    reading: str  # SUPPORTED, LEAN or CANT_TELL


def score_matrix(scores: Sequence[float] | Sequence[Sequence[float]] | np.ndarray) -> np.ndarray:
    """Scores as a float matrix, runs x tasks; one scalar per run becomes a single task."""
    matrix = np.asarray(scores, dtype=np.float64)
    if matrix.ndim == 1:
        matrix = matrix[:, None]
    if matrix.ndim != 2 or matrix.size == 0:
        raise ValueError(f"scores must be a non-empty runs x tasks matrix, got shape {matrix.shape}")
    if not np.isfinite(matrix).all():
        raise ValueError("scores must be finite")
    return matrix


def pooled(groups: Sequence[np.ndarray | Sequence]) -> np.ndarray:
    """The runs of several strategies as one group (rows stacked); every group must have the same tasks."""
    return np.vstack([score_matrix(group) for group in groups])  # refuses groups of different tasks


def iqm(scores) -> float:
    """The interquartile mean of all run x task scores pooled (rliable's, scipy's trim_mean at 0.25)."""
    return float(stats.trim_mean(score_matrix(scores).ravel(), IQM_TRIM))


def probability_of_improvement(x, y) -> float:
    """P(X > Y): per task, the share of run pairs with X above Y (ties one half), averaged over tasks."""
    x, y = score_matrix(x), score_matrix(y)
    if x.shape[1] != y.shape[1]:
        raise ValueError(f"groups must share their tasks, got {x.shape[1]} and {y.shape[1]}")
    return float(_improvement(x, y))


def stratified_replicates(scores, replicates: int, rng: np.random.Generator) -> np.ndarray:
    """(replicates, runs, tasks): each task's column redrawn from its own runs, independently per task."""
    matrix = score_matrix(scores)
    runs, tasks = matrix.shape
    drawn = rng.integers(0, runs, size=(replicates, runs, tasks))
    return matrix[drawn, np.arange(tasks)]


def iqm_estimate(scores, bootstrap: Bootstrap | None = None) -> Estimate:
    """The IQM with its stratified bootstrap interval."""
    bootstrap = bootstrap or Bootstrap()
    drawn = stratified_replicates(scores, bootstrap.replicates, np.random.default_rng(bootstrap.seed))
    values = stats.trim_mean(drawn.reshape(bootstrap.replicates, -1), IQM_TRIM, axis=1)
    return Estimate(iqm(scores), percentile_interval(values, bootstrap.confidence))


def improvement_estimate(x, y, bootstrap: Bootstrap | None = None) -> Estimate:
    """P(X > Y) with its interval; X and Y are redrawn independently (they are separate trainings)."""
    bootstrap = bootstrap or Bootstrap()
    point = probability_of_improvement(x, y)
    rng = np.random.default_rng(bootstrap.seed)
    drawn_x = stratified_replicates(x, bootstrap.replicates, rng)
    drawn_y = stratified_replicates(y, bootstrap.replicates, rng)
    return Estimate(point, percentile_interval(_improvement(drawn_x, drawn_y), bootstrap.confidence))


def mann_whitney_p(a, b) -> float:
    """One-sided p-value that A's runs score above B's, each run scored by its mean over the tasks: the share
    of all splits of the pooled runs into n and m whose U is at least the one observed (ties count one half),
    or the normal approximation past EXACT_ARRANGEMENTS splits."""
    a, b = score_matrix(a).mean(axis=1), score_matrix(b).mean(axis=1)
    if math.comb(len(a) + len(b), len(a)) > EXACT_ARRANGEMENTS:
        return float(stats.mannwhitneyu(a, b, alternative="greater", method="asymptotic").pvalue)
    ranks = stats.rankdata(np.concatenate([a, b]))  # midranks: a rank sum fixes U, ties included
    observed = ranks[:len(a)].sum()
    at_least = total = 0
    for chunk in _splits(len(ranks), len(a)):
        sums = ranks[chunk].sum(axis=1)
        at_least += int((sums >= observed - 1e-9).sum())
        total += len(sums)
    return at_least / total


def _splits(runs: int, chosen: int, chunk: int = 65_536):
    """Every choice of `chosen` of `runs` indices, as (k, chosen) index arrays of at most `chunk` rows."""
    combinations = itertools.combinations(range(runs), chosen)
    while block := list(itertools.islice(combinations, chunk)):
        yield np.array(block, dtype=np.intp)


def reading(p_value: float, improvement: Estimate) -> str:
    """The claims rule of the module docstring."""
    if p_value < SIGNIFICANCE and improvement.interval.low > NO_IMPROVEMENT:
        return SUPPORTED
    if improvement.point > NO_IMPROVEMENT:
        return LEAN
    return CANT_TELL


def claim(a, b, bootstrap: Bootstrap | None = None) -> Claim:
    """Read the claim "A beats B" from the two groups' score matrices (pool strategies with ``pooled``)."""
    a, b = score_matrix(a), score_matrix(b)
    p_value = mann_whitney_p(a, b)
    improvement = improvement_estimate(a, b, bootstrap)
    return Claim(len(a), len(b), p_value, improvement, reading(p_value, improvement))


def reverse_claim(a, b, bootstrap: Bootstrap | None = None) -> Claim:
    """Read "B beats A" where a claim "A beats B" found B ahead. That direction was chosen on seeing the runs,
    so the rule reads it with the two-sided p-value (twice the one-sided, at most 1)."""
    found = claim(b, a, bootstrap)
    p_value = min(1.0, 2 * found.p_value)
    return replace(found, p_value=p_value, reading=reading(p_value, found.improvement))


def smallest_p_value(n: int, m: int) -> float:
    """The least one-sided exact Mann-Whitney p-value of n runs against m: all n above all m, 1 / C(n + m, n)."""
    if n < 1 or m < 1:
        raise ValueError(f"each side needs a run, got {n} and {m}")
    return 1 / math.comb(n + m, n)


def seeds_to_support(significance: float = SIGNIFICANCE) -> int:
    """The fewest seeds a side (equal on both) with which a pairwise claim can reach p < significance."""
    if not 0.0 < significance < 1.0:
        raise ValueError(f"significance must lie in (0, 1), got {significance}")
    n = 1
    while smallest_p_value(n, n) >= significance:
        n += 1
    return n


def _improvement(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """P(X > Y) of (..., runs, tasks) arrays, one per leading index: all run pairs compared on each task."""
    left, right = x[..., :, None, :], y[..., None, :, :]
    wins = (left > right).mean(axis=(-3, -2)) + 0.5 * (left == right).mean(axis=(-3, -2))
    return wins.mean(axis=-1)

