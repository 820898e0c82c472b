"""Performance profiles: the share of evaluation episodes longer than x steps, per strategy, with bands.

One curve per pooled row of the comparison (a strategy's greedy episodes over
its seeds, and the random policy), one panel per start set and replay
capacity. The band at each x is the percentile interval of the same two-stage
bootstrap as the tables (common/analysis/intervals.py): runs resampled whole,
then each run's trials within each start. A curve that stays high to the right
drives long; the value at the cap is the CFR.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np

from common.analysis.figures import strategy_colour
from common.analysis.intervals import Bootstrap, bootstrap_weights, profile_band
from deploy.studies.comparison import STRATEGY_NAMES, ComparisonRow

POINTS = 201  # thresholds per curve, from 0 to the longest episode


def plot_performance_profiles(rows: Sequence[ComparisonRow], path: Path, bootstrap: Bootstrap | None = None) -> None:
    """Draws the pooled rows; a panel per (start set, capacity), in the rows' order."""
    bootstrap = bootstrap or Bootstrap()
    pooled = [row for row in rows if row.pooled and row.cell is not None]
    if not pooled:
        raise ValueError("no pooled rows to draw a performance profile of")
    panels = list(dict.fromkeys((row.start_set, row.capacity) for row in pooled))
    longest = max(float(row.cell.lengths.max()) for row in pooled)
    thresholds = np.linspace(0.0, longest, POINTS)
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    figure, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4), dpi=90, squeeze=False)
    for ax, (start_set, capacity) in zip(axes[0], panels):
        for row in pooled:
            if (row.start_set, row.capacity) != (start_set, capacity):
                continue
            weights = bootstrap_weights(row.cell.runs, row.cell.starts, bootstrap.replicates,
                                        np.random.default_rng(bootstrap.seed))
            observed, low, high = profile_band(row.cell.lengths, weights, thresholds, bootstrap.confidence)
            colour = strategy_colour(row.strategy)
            label = f"{STRATEGY_NAMES.get(row.strategy, row.strategy)} ({row.runs} run{'s' * (row.runs > 1)})"
            ax.plot(thresholds, observed, color=colour, linewidth=1.2, label=label)
            ax.fill_between(thresholds, low, high, color=colour, alpha=0.2, linewidth=0)
        ax.set(title=f"{start_set} starts, replay capacity {capacity:,d}", xlabel="episode length x (steps)",
               ylabel="share of episodes longer than x", ylim=(-0.02, 1.02))
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    figure.suptitle(f"performance profiles, {100 * bootstrap.confidence:g}% bootstrap bands over runs and trials")
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    plt.close(figure)
