"""Paired comparisons across runs: two readings of the same runs (a policy kind against the online one), or two
runs that differ in one setting only (buffer 1,000 against 2,000 at the same strategy and seed).

* The Wilcoxon signed-rank test of the differences x_i - y_i: zero differences are dropped (Wilcoxon's own
  rule), the others ranked by size with midranks for ties, W+ the sum of the positive ones' ranks. Its
  p-value is exact, ties included: the share of all 2^n sign patterns of the ranks whose W+ is at least the
  observed (one-sided, "greater"), or as extreme in either direction (two-sided, twice the smaller tail, at
  most 1); the normal approximation only past EXACT_PAIRS pairs. n pairs can give no two-sided p below
  2 / 2^n: 5 pairs at best 0.0625.
* P(X > Y) of pairs: the share of pairs whose x is above its y, a tie one half.
* Its interval: a stratified bootstrap over pairs, each stratum (a strategy) redrawn from its own pairs,
  uniformly with replacement, as rliable stratifies by task (common/analysis/across_seeds.py).
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from scipy import stats

from common.analysis.across_seeds import Estimate
from common.analysis.intervals import Bootstrap, percentile_interval

EXACT_PAIRS = 22  # up to 2^22 sign patterns, enumerated in chunks
_CHUNK = 1 << 16


def _pairs(x, y) -> tuple[np.ndarray, np.ndarray]:
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if x.shape != y.shape or x.ndim != 1 or not x.size:
        raise ValueError(f"paired readings must be two equal non-empty lists, got shapes {x.shape} and {y.shape}")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("paired readings must be finite")
    return x, y


def signed_rank_p(x, y, alternative: str = "two-sided") -> float:
    """The Wilcoxon signed-rank p-value of the pairs (x_i, y_i): "greater" (x above y), or "two-sided"."""
    if alternative not in ("greater", "two-sided"):
        raise ValueError(f"alternative: greater or two-sided, not {alternative!r}")
    x, y = _pairs(x, y)
    differences = (x - y)[x != y]
    if not differences.size:
        return 1.0
    ranks = stats.rankdata(np.abs(differences))
    observed = float(ranks[differences > 0].sum())
    upper, lower = _tails(ranks, observed)
    if alternative == "greater":
        return upper
    return min(1.0, 2 * min(upper, lower))


def _tails(ranks: np.ndarray, observed: float) -> tuple[float, float]:
    """P(W+ >= observed) and P(W+ <= observed) under random signs."""
    n = len(ranks)
    if n > EXACT_PAIRS:
        mean, spread = ranks.sum() / 2, math.sqrt((ranks ** 2).sum() / 4)
        return (float(stats.norm.sf((observed - 0.5 - mean) / spread)),
                float(stats.norm.cdf((observed + 0.5 - mean) / spread)))
    at_least = at_most = 0
    bits = np.arange(n)
    for start in range(0, 1 << n, _CHUNK):
        patterns = np.arange(start, min(start + _CHUNK, 1 << n))
        sums = (((patterns[:, None] >> bits) & 1) * ranks).sum(axis=1)
        at_least += int((sums >= observed - 1e-9).sum())
        at_most += int((sums <= observed + 1e-9).sum())
    return at_least / (1 << n), at_most / (1 << n)


def paired_improvement(x, y) -> float:
    """P(X > Y) over the pairs: the share with x above y, a tie one half."""
    x, y = _pairs(x, y)
    return float(np.mean((x > y) + 0.5 * (x == y)))


def paired_improvement_estimate(x, y, strata: Sequence[str] | None = None,
                                bootstrap: Bootstrap | None = None) -> Estimate:
    """P(X > Y) with its interval: each stratum's pairs redrawn from its own (one stratum where none given)."""
    x, y = _pairs(x, y)
    bootstrap = bootstrap or Bootstrap()
    labels = np.asarray(strata if strata is not None else [""] * len(x))
    if labels.shape != x.shape:
        raise ValueError(f"one stratum a pair: {len(labels)} strata for {len(x)} pairs")
    wins = (x > y) + 0.5 * (x == y)
    rng = np.random.default_rng(bootstrap.seed)
    drawn = np.concatenate([rng.choice(np.flatnonzero(labels == label), size=(bootstrap.replicates,
                                                                              int((labels == label).sum())))
                            for label in dict.fromkeys(labels.tolist())], axis=1)
    values = wins[drawn].mean(axis=1)
    return Estimate(float(wins.mean()), percentile_interval(values, bootstrap.confidence))
