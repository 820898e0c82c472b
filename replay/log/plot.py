"""Training curves of a log, as the paper draws them, into one PNG (matplotlib, Agg backend).

Four panels: the mean episode return over the last 100 episodes against the
episode count; the epsilon each episode was acted with against the environment
steps of all episodes so far (both from the actors' EpisodeRecords, in the order
the recorder received them); the learner's loss and the mean |loss_k - loss_k-1|
of consecutive updates against updates (both averaged over each of the learner's
report periods).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from replay.log.export import Tables

RETURN_WINDOW = 100  # episodes, the paper's "average reward per 100 episodes"
LEARNER_METRICS = "metrics/learner/0"  # the learner's Stats key below the run


def trailing_mean(values: list[float], window: int) -> np.ndarray:
    """Mean of the last `window` values at each position (fewer at the start)."""
    sums = np.cumsum(np.asarray(values, dtype=np.float64))
    counts = np.minimum(np.arange(1, len(values) + 1), window)
    earlier = np.concatenate([np.zeros(window), sums])[: len(values)]
    return (sums - earlier) / counts


def finite_series(rows: list[dict], x_name: str, y_name: str) -> tuple[list[float], list[float]]:
    """(x, y) pairs of rows where both are finite numbers."""
    pairs = [(row.get(x_name), row.get(y_name)) for row in rows]
    kept = [(x, y) for x, y in pairs if _finite(x) and _finite(y)]
    return [x for x, _ in kept], [y for _, y in kept]


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def plot_training(tables: Tables, path: Path, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    learner = tables.stats.get(LEARNER_METRICS, [])
    figure, axes = plt.subplots(2, 2, figsize=(10, 6.5), dpi=90)
    returns = [row["episode_return"] for row in tables.episodes]
    ax = axes[0, 0]
    ax.plot(np.arange(1, len(returns) + 1), trailing_mean(returns, RETURN_WINDOW), color="tab:blue")
    ax.set(title=f"mean return of the last {RETURN_WINDOW} episodes", xlabel="episodes", ylabel="return")
    ax = axes[0, 1]
    steps = np.cumsum([row["length"] for row in tables.episodes])
    ax.step(steps, [row["epsilon"] for row in tables.episodes], where="post", color="tab:orange")
    ax.set(title="epsilon the actors used against env steps", xlabel="env steps", ylabel="epsilon")
    for ax, (x_name, y_name, y_label, colour) in zip(
            (axes[1, 0], axes[1, 1]),
            (("updates", "loss", "loss", "tab:green"), ("updates", "loss_abs_diff", "|Δloss|", "tab:red"))):
        xs, ys = finite_series(learner, x_name, y_name)
        ax.plot(xs, ys, color=colour, marker="." if len(xs) < 50 else None)
        ax.set(title=f"{y_label} against {x_name.replace('_', ' ')}", xlabel=x_name.replace("_", " "), ylabel=y_label)
        if y_name == "loss_abs_diff" and ys and min(ys) > 0:
            ax.set_yscale("log")
    for ax in axes.flat:
        ax.grid(alpha=0.3)
    figure.suptitle(title)
    figure.tight_layout()
    figure.savefig(path)
    plt.close(figure)
