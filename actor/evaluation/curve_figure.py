"""The figure of a greedy learning curve (actor/evaluation/curve.py): mean length and CFR against wall time and
env steps, a line per start set with its interval band."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

from common.analysis.plotting import finish_figure, pyplot

PANELS = (("mean_length", 1.0, "greedy mean length (steps)"), ("cfr", 100.0, "greedy CFR (%)"))
SET_COLOURS = {"train": "tab:blue", "test": "tab:orange"}


def unbridged(points: Sequence[dict], rows: Sequence[dict]) -> list[list[dict]]:
    """One start set's rows, by updates, split where a kept policy of the curve lacks a row of that set: a
    line does not bridge policies evaluated on the other set only."""
    order = {updates: index for index, updates in enumerate(sorted({int(row["updates"]) for row in rows}))}
    segments: list[list[dict]] = []
    for row in points:
        if not segments or order[int(row["updates"])] != order[int(segments[-1][-1]["updates"])] + 1:
            segments.append([])
        segments[-1].append(row)
    return segments


def plot_curve(rows: Sequence[dict], path: Path, title: str) -> None:
    """Mean length and CFR of the greedy policy against wall time and env steps, a line per start set,
    its band the rows' intervals over the trials."""
    plt = pyplot()
    hours = max(float(row["wall_s"]) for row in rows) > 2 * 3600  # else minutes
    x_axes = (("wall_s", 1 / 3600 if hours else 1 / 60, f"wall time since the run started ({'h' if hours else 'min'})"),
              ("env_steps", 1.0, "env steps"))
    figure, axes = plt.subplots(2, 2, figsize=(10, 6.5), dpi=90)
    for panel_axes, (statistic, scale, y_label) in zip(axes, PANELS):
        for ax, (x_column, x_scale, x_label) in zip(panel_axes, x_axes):
            for start_set, colour in SET_COLOURS.items():
                points = sorted((row for row in rows if row["start_set"] == start_set), key=lambda r: int(r["updates"]))
                for number, segment in enumerate(unbridged(points, rows)):
                    x = [x_scale * float(row[x_column]) for row in segment]
                    y, low, high = ([scale * float(row[key]) for row in segment]
                                    for key in (statistic, f"{statistic}_low", f"{statistic}_high"))
                    ax.plot(x, y, color=colour, marker=".", label=None if number else start_set)
                    if all(math.isfinite(value) for value in low + high):
                        ax.fill_between(x, low, high, color=colour, alpha=0.2, linewidth=0)
            ax.set(xlabel=x_label, ylabel=y_label)
    finish_figure(plt, figure, axes.flat, path, title)
