"""matplotlib for the PNG figures: the Agg backend (files only, no display), the finish every figure shares
(compact tick labels for counts in the thousands), and the trailing mean the training curves are smoothed with."""

from __future__ import annotations

from pathlib import Path

import numpy as np

RETURN_WINDOW = 100  # episodes, the paper's "average reward per 100 episodes"


def pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def finish_figure(plt, figure, axes, path: Path, title: str) -> None:
    """A grid and a legend (where lines have labels) on each panel, the title, then the PNG, and the figure closed."""
    for ax in axes:
        ax.grid(alpha=0.3)
        if ax.get_xscale() == "linear":
            from matplotlib.ticker import FuncFormatter
            ax.xaxis.set_major_formatter(FuncFormatter(tick_text(max(map(abs, ax.get_xlim())))))
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    figure.suptitle(title, fontsize=10)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    plt.close(figure)


def tick_text(largest: float):
    """Tick labels for an axis reaching `largest`: in M from a million, in k from 10,000, so that 140,000 env
    steps read "140k" and neighbouring labels do not run together."""
    scale, suffix = next(((unit, name) for unit, name, start in ((1e6, "M", 1e6), (1e3, "k", 1e4)) if largest >= start),
                         (1, ""))
    return lambda value, _position=None: f"{value / scale:g}{suffix}" if value else "0"


def trailing_mean(values: list[float], window: int) -> np.ndarray:
    """Mean of the last `window` values at each position (fewer at the start)."""
    sums = np.cumsum(np.asarray(values, dtype=np.float64))
    counts = np.minimum(np.arange(1, len(values) + 1), window)
    earlier = np.concatenate([np.zeros(window), sums])[: len(values)]
    return (sums - earlier) / counts
