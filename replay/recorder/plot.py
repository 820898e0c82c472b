"""Training curves of a log into one PNG (matplotlib, Agg backend), from the series of ``scalars.py``.

Four panels: the mean episode return over the last 100 episodes and the epsilon each
episode was acted with, beside the share of actions that were not greedy where the actors
counted them (all from the actors' EpisodeRecords, in the order the recorder received them); the learner's loss and the mean |loss_k - loss_k-1| of
consecutive updates (both averaged over each of the learner's report periods). By
default each is drawn as the paper draws it: return against episodes, epsilon against
env steps, both losses against updates; with x = "env_steps" or "episodes" every panel
is drawn against that axis. A dashed line marks where updates started: the env steps at
which the replay served the first batch, or the episodes recorded by then.
"""

from __future__ import annotations

import bisect
from pathlib import Path

from common.analysis.plotting import RETURN_WINDOW, finish_figure, pyplot
from replay.recorder.scalars import EPSILON, LOSS, LOSS_ABS_DIFF, OFF_GREEDY_MEAN, RETURN_MEAN, UPDATES_START, Series

PANELS = (  # tag, title, y label, colour, the paper's x axis
    (RETURN_MEAN, f"mean return of the last {RETURN_WINDOW} episodes", "return", "tab:blue", "episodes"),
    (EPSILON, "epsilon the actors used", "epsilon", "tab:orange", "env_steps"),
    (LOSS, "loss", "loss", "tab:green", "updates"),
    (LOSS_ABS_DIFF, "|Δloss|", "|Δloss|", "tab:red", "updates"),
)
PLOTTED = frozenset(tag for tag, *_ in PANELS) | {UPDATES_START, OFF_GREEDY_MEAN}


def updates_start(series: Series) -> dict[str, float] | None:
    """Where updates started, in env steps and in episodes recorded by then; None before they start."""
    marks = series.get(UPDATES_START)
    if not marks:
        return None
    env_steps = marks[0].value
    episode_steps = [point.env_steps for point in series.get(RETURN_MEAN, [])]
    return {"env_steps": env_steps, "episodes": bisect.bisect_right(episode_steps, env_steps)}


def plot_training(series: Series, path: Path, title: str, x: str | None = None) -> None:
    """x: "env_steps" or "episodes" for every panel; None for the paper's axis of each."""
    plt = pyplot()
    start = updates_start(series)
    figure, axes = plt.subplots(2, 2, figsize=(10, 6.5), dpi=90)
    for ax, (tag, name, y_label, colour, paper_axis) in zip(axes.flat, PANELS):
        axis = x or paper_axis
        points = series.get(tag, [])
        xs, ys = [getattr(point, axis) for point in points], [point.value for point in points]
        if tag == EPSILON:
            ax.step(xs, ys, where="post", color=colour, label="epsilon")
            off_greedy = series.get(OFF_GREEDY_MEAN, [])
            if off_greedy:  # what the strategy explored: a softmax sample is often the greedy action
                ax.plot([getattr(point, axis) for point in off_greedy], [point.value for point in off_greedy],
                        color="tab:purple", label=f"actions not greedy ({RETURN_WINDOW} episodes)")
        else:
            ax.plot(xs, ys, color=colour, marker="." if tag != RETURN_MEAN and len(xs) < 50 else None)
        label = axis.replace("_", " ")
        ax.set(title=name if tag == RETURN_MEAN and x is None else f"{name} against {label}", xlabel=label,
               ylabel=y_label)
        if tag == LOSS_ABS_DIFF and ys and min(ys) > 0:
            ax.set_yscale("log")
        if start is not None and axis != "updates":
            ax.axvline(start[axis], color="0.4", linestyle="--", linewidth=1, label="updates start")
    finish_figure(plt, figure, list(axes.flat), path, title)
