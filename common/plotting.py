"""matplotlib for the PNG figures: the Agg backend (files only, no display) and the finish every figure shares."""

from __future__ import annotations

from pathlib import Path


def pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def finish_figure(plt, figure, axes, path: Path, title: str) -> None:
    """A grid and a legend (where lines have labels) on each panel, the title, then the PNG, and the figure closed."""
    for ax in axes:
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    figure.suptitle(title, fontsize=10)
    figure.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    plt.close(figure)
