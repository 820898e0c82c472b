"""The paper's comparison figures, several runs to a figure, as PNGs (matplotlib, Agg backend).

A run's training curves come from its logs (``RunCurves``, read by replay/recorder/run_curves.py).
The figures:

* ``plot_reward_curves``: mean return of the last 100 episodes against episodes,
  one panel per replay capacity (the paper's "average reward per 100 episodes");
* ``plot_epsilon``: the epsilon each episode was acted with against the env
  steps of all episodes so far, in the paper's three panels (deterministic
  epsilon-greedy, adaptive epsilon-greedy, Max-Boltzmann); Softmax has no epsilon;
* ``plot_loss_differences``: the learner's mean |loss_k - loss_k-1| of each
  report period against updates, smoothed by a trailing mean over the last
  ``LOSS_WINDOW`` reports (the paper draws a spline), log scale;
* ``plot_reward_bins``: grouped bars of the share of step rewards per bin, one
  group per bin, one bar per entry (the evaluation's strategies and the random
  policy), one panel per replay capacity.

In the training figures each strategy is one line, the mean over its runs
(seeds), with a band over their range (``seed_band``).
"""

from __future__ import annotations

import math

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from common.analysis.plotting import RETURN_WINDOW, finish_figure, pyplot, trailing_mean
from common.exploration.names import DISPLAY_NAMES, STRATEGIES, epsilon_groups, strategy_rank

LOSS_WINDOW = 10  # learner reports (each the mean over learner.log_period_s) per point of the smoothed curve
EPSILON_PANELS = tuple(epsilon_groups().items())  # (title, strategies) of each panel
EPSILON_STRATEGIES = tuple(strategy for _, members in EPSILON_PANELS for strategy in members)
RANDOM_COLOUR = "0.6"
PRIVILEGED_COLOUR = "0.15"
BAND_NOTE = "\n(a line per strategy: the mean over its runs; band: their range)"


@dataclass
class RunCurves:
    """One run's training curves, read from its logs (replay/recorder/run_curves.py)."""

    label: str
    strategy: str
    capacity: int  # replay.capacity, episodes
    episode_returns: list[float] = field(default_factory=list)
    episode_lengths: list[int] = field(default_factory=list)
    episode_epsilons: list[float] = field(default_factory=list)
    episode_off_greedy: list[int] = field(default_factory=list)  # actions not argmax Q; -1 where not counted
    learner_updates: list[float] = field(default_factory=list)
    loss_abs_diffs: list[float] = field(default_factory=list)  # one per learner report, NaN-free

    @property
    def off_greedy_share(self) -> float:
        """The share of actions that were not argmax Q over the episodes whose actors counted them (those acted
        wholly with the learner's weights); nan where none did. A count outside 0..length (a damaged file) is
        left out like an uncounted one."""
        counted = [(off, length) for off, length in zip(self.episode_off_greedy, self.episode_lengths)
                   if 0 <= off <= length]
        steps = sum(length for _, length in counted)
        return sum(off for off, _ in counted) / steps if steps else math.nan


# --- the figures -------------------------------------------------------------------------------------

def strategy_colour(strategy: str) -> str:
    """One colour per strategy, the same in every figure; greys for the baselines (the evaluation's
    policies "random" and "privileged")."""
    if strategy in STRATEGIES:
        return f"C{STRATEGIES.index(strategy)}"
    return PRIVILEGED_COLOUR if strategy == "privileged" else RANDOM_COLOUR


Series = tuple[np.ndarray, np.ndarray]  # (x, y) of one run, x increasing


def plot_reward_curves(runs: Sequence[RunCurves], path: Path, window: int = RETURN_WINDOW) -> None:
    def series(run: RunCurves) -> Series | None:
        returns = run.episode_returns
        return (np.arange(1, len(returns) + 1), trailing_mean(returns, window)) if returns else None

    _plot_by_capacity(runs, path, series, f"mean return of the last {window} training episodes",
                      xlabel="episodes", ylabel="return")


def plot_loss_differences(runs: Sequence[RunCurves], path: Path, window: int = LOSS_WINDOW) -> None:
    def series(run: RunCurves) -> Series | None:
        if not run.loss_abs_diffs:
            return None
        return np.asarray(run.learner_updates, dtype=float), trailing_mean(run.loss_abs_diffs, window)

    _plot_by_capacity(runs, path, series, f"|loss_k - loss_k-1|, trailing mean of the last {window} learner reports",
                      xlabel="updates", ylabel="|Δloss|", log=True)


def plot_epsilon(runs: Sequence[RunCurves], path: Path) -> None:
    """Runs of strategies without an epsilon (softmax) are left out; at least one must have one."""
    panels = [(title, [run for run in runs if run.strategy in members]) for title, members in EPSILON_PANELS]
    panels = [(title, members) for title, members in panels if members]
    if not panels:
        raise ValueError(f"no run of an epsilon-based strategy ({', '.join(EPSILON_STRATEGIES)})")
    plt = pyplot()
    figure, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4), dpi=90, squeeze=False)
    for ax, (title, members) in zip(axes[0], panels):
        _draw_cells(ax, members, lambda run: (np.cumsum(run.episode_lengths), np.asarray(run.episode_epsilons))
                    if run.episode_lengths else None)
        ax.set(title=title, xlabel="env steps", ylabel="epsilon", ylim=(-0.02, 1.02))
    finish_figure(plt, figure, axes[0], path, "epsilon the actors used against env steps" + BAND_NOTE)


def seed_band(series: Sequence[Series], points: int = 200) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The runs of one cell (strategy, capacity) on one x: (x, mean, low, high) across the runs.

    One run is drawn as it is. Several are interpolated onto `points` x values over the range they all
    cover, so that the band never extrapolates a run past its end."""
    if len(series) == 1:
        x, y = series[0]
        return x, y, y, y
    start, stop = max(float(x[0]) for x, _ in series), min(float(x[-1]) for x, _ in series)
    if stop < start:
        raise ValueError(f"the runs share no stretch of x: [{start:g}, {stop:g}]")
    grid = np.linspace(start, stop, points)
    values = np.stack([np.interp(grid, x, y) for x, y in series])
    return grid, values.mean(axis=0), values.min(axis=0), values.max(axis=0)


def plot_reward_bins(panels: dict[str, Sequence[tuple[str, str, Sequence[float]]]], bin_labels: Sequence[str],
                     path: Path, title: str) -> None:
    """panels: panel title -> bars as (label, strategy for the colour, share of steps per bin)."""
    if not panels or not all(panels.values()):
        raise ValueError("every panel of the reward-bin chart needs at least one bar")
    for bars in panels.values():
        for label, _, shares in bars:
            if len(shares) != len(bin_labels):
                raise ValueError(f"{label}: {len(shares)} shares for {len(bin_labels)} bins")
    plt = pyplot()
    figure, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4), dpi=90, squeeze=False)
    positions = np.arange(len(bin_labels))
    for ax, (panel_title, bars) in zip(axes[0], panels.items()):
        width = 0.8 / len(bars)
        for number, (label, strategy, shares) in enumerate(bars):
            ax.bar(positions - 0.4 + width * (number + 0.5), 100 * np.asarray(shares), width, label=label,
                   color=strategy_colour(strategy))
        ax.set_xticks(positions, bin_labels)
        ax.set(title=panel_title, xlabel="step reward", ylabel="% of steps", ylim=(0, 100))
    finish_figure(plt, figure, axes[0], path, title)


# --- layout --------------------------------------------------------------------------------------------

def _plot_by_capacity(runs: Sequence[RunCurves], path: Path, series, title: str, xlabel: str, ylabel: str,
                      log: bool = False) -> None:
    """One panel per replay capacity; in it, a line per strategy: the mean of its runs' series(run), with
    the band of their range when it has several (seeds)."""
    if not runs:
        raise ValueError("no runs to plot")
    capacities = sorted({run.capacity for run in runs})
    plt = pyplot()
    figure, axes = plt.subplots(1, len(capacities), figsize=(6 * len(capacities), 4), dpi=90, squeeze=False)
    for ax, capacity in zip(axes[0], capacities):
        if _draw_cells(ax, [run for run in runs if run.capacity == capacity], series) and log:
            ax.set_yscale("log")
        ax.set(title=f"replay capacity {capacity:,d} episodes", xlabel=xlabel, ylabel=ylabel)
    finish_figure(plt, figure, axes[0], path, title + BAND_NOTE)


def _draw_cells(ax, runs: Sequence[RunCurves], series) -> bool:
    """A line per strategy of these runs, mean and range over its runs; False if nothing had data."""
    drawn = False
    for strategy in sorted({run.strategy for run in runs}, key=strategy_rank):
        found = [one for one in (series(run) for run in runs if run.strategy == strategy) if one is not None]
        if not found:
            continue
        x, mean, low, high = seed_band(found)
        colour = strategy_colour(strategy)
        label = DISPLAY_NAMES.get(strategy, strategy) + (f" ({len(found)} runs)" if len(found) > 1 else "")
        ax.plot(x, mean, label=label, color=colour, linewidth=1)
        if len(found) > 1:
            ax.fill_between(x, low, high, color=colour, alpha=0.2, linewidth=0)
        drawn = True
    return drawn
