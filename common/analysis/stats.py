"""Statistics of an evaluation: per-episode records in, the rows of the paper's tables out.

Pure functions over plain records, so every figure can be checked by hand.
Conventions (the paper does not spell them out):

* CFR (collision-free rate) is the share of episodes that reach the step cap.
  An episode that ends before the cap for any reason (a collision, leaving the
  road, or stalling: no progress along the road over the simulator's window)
  is not collision-free in this sense: it did not reach the cap.
* How an episode ended is the simulator's ``info["end"]`` on the terminating
  step ("collision", "offroad" or "stalled"); a simulator that does not report
  it is read from its ``collision`` and ``offroad`` flags. An episode cut at the
  step cap ended by "cap".
* Progress is the simulator's ``info["progress_m"]`` at the episode's last
  step: metres driven along the road network in the direction of travel. A
  simulator that does not report it gives NaN, not 0 (0 would claim that the
  car did not move); a row whose episodes have no progress shows "–".
* Coverage is the number of distinct streets and of distinct junctions an
  episode visited, from the simulator's ``info["streets_visited"]`` after its
  last step (a street counts once driven along, a junction once turned at or
  crossed: actor/sim/neighbourhood.py, ``places_reached``). A driver that
  loops one block reaches the cap with full progress over 4 streets and 4
  junctions; these columns tell it from one that explores. NaN where the
  simulator does not report the places.
* The standard deviation of episode lengths is the population one (ddof = 0,
  numpy's default).
* Mean reward per step and the reward-bin shares pool every step of every
  episode of the group (an episode of 2,000 steps weighs 2,000 times one of a
  single step), as the paper's figure of step-reward shares does.
* Reward bins are half-open [a, b) except the last, which is closed [a, b], so
  a reward of exactly 1 (the car on the centre-line) falls in the top bin.
* The interquartile mean (IQM) of episode lengths is the mean of the middle half
  of the lengths (common/analysis/intervals.py), robust to a few episodes at
  the cap or a few crashes at the start.
* Confidence intervals come from the two-stage stratified bootstrap of
  common/analysis/intervals.py: training runs resampled whole, then each
  run's trials within each start.
"""

from __future__ import annotations

import hashlib
import math
from collections import defaultdict
from dataclasses import dataclass
from typing import Hashable, Iterable, Sequence

import numpy as np

from common.analysis.intervals import Bootstrap, Cell, Interval, cell_intervals, cell_statistics

TERMINAL_REASONS = ("collision", "offroad", "stalled")  # what the simulator's info["end"] may say
END_REASONS = (*TERMINAL_REASONS, "cap")


@dataclass(frozen=True)
class EvaluationEpisode:
    """One finished evaluation episode."""

    policy: str  # "greedy", "random" or "privileged"
    start_set: str  # "train" or "test"
    start_index: int
    trial: int  # 0 .. episodes_per_start - 1
    seed: int
    length: int  # steps taken
    end: str  # one of END_REASONS; a collision wins over leaving the road on the same step
    episode_return: float  # sum of the step rewards
    reward_bin_counts: tuple[int, ...]  # steps whose reward fell in each bin
    actions_digest: str  # equal digests mean the same action sequence, hence the same trajectory
    progress_m: float = math.nan  # metres along the road network; NaN when the simulator does not say
    streets: float = math.nan  # distinct streets visited (a count); NaN when the simulator does not say
    junctions: float = math.nan  # distinct junctions visited (a count); NaN when the simulator does not say
    end_x: float = math.nan  # the car's pose at its last step (metres, radians); NaN when the simulator does not say
    end_y: float = math.nan
    end_heading: float = math.nan
    end_place: str = ""  # the street or junction it ended on; "" when the simulator does not say
    hit: str = ""  # what a collision touched (actor/sim/collision_site.py); "" for other ends

    @property
    def collision_free(self) -> bool:
        return self.end == "cap"


SITE_FIELDS = ("end_x", "end_y", "end_heading", "end_place", "hit")  # where an episode ended; episodes.csv's columns


@dataclass(frozen=True)
class SetSummary:
    """One table row: one policy on one start set, pooled over one or more training runs."""

    policy: str
    start_set: str
    runs: int  # training runs (seeds) whose episodes the row pools
    episodes: int
    mean_length: float
    iqm_length: float  # interquartile mean of the lengths
    std_length: float
    min_length: int
    max_length: int
    cfr: float  # share of episodes reaching the cap
    collision_share: float  # share of episodes ended by a collision
    offroad_share: float  # share of episodes ended by leaving the road
    stalled_share: float  # share of episodes ended for making no progress
    mean_progress_m: float  # metres along the road per episode; NaN when the simulator does not report it
    mean_streets: float  # distinct streets visited per episode; NaN when the simulator does not report them
    mean_junctions: float  # distinct junctions visited per episode; NaN likewise
    mean_reward_per_step: float
    reward_shares: tuple[float, ...]  # share of all steps whose reward fell in each bin
    distinct_per_start: float  # distinct trajectories among the trials of a start, averaged over starts
    intervals: dict[str, Interval]  # one per intervals.STATISTICS name


def reward_bin_counts(rewards: Sequence[float] | np.ndarray, edges: Sequence[float]) -> tuple[int, ...]:
    """How many rewards fall in each bin [e0, e1), [e1, e2), ..., [e_{n-1}, e_n]."""
    values = np.asarray(rewards, dtype=np.float64)
    edges = np.asarray(edges, dtype=np.float64)
    outside = (values < edges[0]) | (values > edges[-1])
    if outside.any():
        raise ValueError(f"reward {values[outside][0]!r} lies outside the bins [{edges[0]}, {edges[-1]}]")
    # side="right" puts a value equal to an inner edge in the bin that starts there; the last
    # edge itself would open a bin of its own, so it is folded into the last bin.
    index = np.minimum(np.searchsorted(edges, values, side="right") - 1, len(edges) - 2)
    return tuple(int(count) for count in np.bincount(index, minlength=len(edges) - 1))


def digest_of_actions(actions: Sequence[int]) -> str:
    """A short fingerprint of an action sequence: in a deterministic simulator, of the trajectory."""
    return hashlib.blake2b(bytes(actions), digest_size=8).hexdigest()


def summarise(episodes: Sequence[EvaluationEpisode], runs: Sequence[Hashable] | None = None,
              bootstrap: Bootstrap | None = None) -> SetSummary:
    """The row of one group of episodes that share a policy and a start set.

    runs: the training run (seed) of each episode when the group pools several;
    the intervals resample them whole (common/analysis/intervals.py).
    """
    if not episodes:
        raise ValueError("cannot summarise an empty group of episodes")
    groups = {(episode.policy, episode.start_set) for episode in episodes}
    if len(groups) != 1:
        raise ValueError(f"a summary row needs one policy and one start set, got {sorted(groups)}")
    lengths = np.array([episode.length for episode in episodes], dtype=np.float64)
    steps = lengths.sum()
    bin_totals = np.sum([episode.reward_bin_counts for episode in episodes], axis=0)
    policy, start_set = groups.pop()
    runs = list(runs) if runs is not None else [0] * len(episodes)
    if len(runs) != len(episodes):
        raise ValueError(f"{len(runs)} run labels for {len(episodes)} episodes")
    cell = episode_cell(episodes, runs)
    point = cell_statistics(cell, np.ones(len(episodes)))
    return SetSummary(
        policy=policy,
        start_set=start_set,
        runs=len(set(runs)),
        episodes=len(episodes),
        mean_length=float(point["mean_length"]),
        iqm_length=float(point["iqm_length"]),
        std_length=float(lengths.std()),
        min_length=int(lengths.min()),
        max_length=int(lengths.max()),
        cfr=float(point["cfr"]),
        collision_share=_share(episodes, lambda episode: episode.end == "collision"),
        offroad_share=_share(episodes, lambda episode: episode.end == "offroad"),
        stalled_share=_share(episodes, lambda episode: episode.end == "stalled"),
        mean_progress_m=float(point["progress_m"]),
        mean_streets=float(point["streets"]),
        mean_junctions=float(point["junctions"]),
        mean_reward_per_step=float(point["reward_per_step"]),
        reward_shares=tuple(float(count / steps) for count in bin_totals),
        distinct_per_start=distinct_trajectories_per_start(episodes),
        intervals=cell_intervals(cell, bootstrap or Bootstrap()),
    )


def episode_cell(episodes: Sequence[EvaluationEpisode], runs: Sequence[Hashable]) -> Cell:
    """The arrays the bootstrap resamples: runs whole, trials within (run, start)."""
    return Cell.of(runs, [(episode.start_set, episode.start_index) for episode in episodes],
                   [episode.length for episode in episodes], [episode.collision_free for episode in episodes],
                   [episode.episode_return for episode in episodes], [episode.progress_m for episode in episodes],
                   streets=[episode.streets for episode in episodes],
                   junctions=[episode.junctions for episode in episodes])


def summarise_all(episodes: Iterable[EvaluationEpisode], bootstrap: Bootstrap | None = None) -> list[SetSummary]:
    """One row per (policy, start set), in the order the groups first appear."""
    groups: dict[tuple[str, str], list[EvaluationEpisode]] = defaultdict(list)
    for episode in episodes:
        groups[(episode.policy, episode.start_set)].append(episode)
    return [summarise(group, bootstrap=bootstrap) for group in groups.values()]


def distinct_trajectories_per_start(episodes: Sequence[EvaluationEpisode]) -> float:
    """The number of different action sequences among the trials of a start, averaged over starts.

    1.0 means every trial from a start repeated the first one exactly.
    """
    digests: dict[tuple[str, int], set[str]] = defaultdict(set)
    for episode in episodes:
        digests[(episode.start_set, episode.start_index)].add(episode.actions_digest)
    return float(np.mean([len(found) for found in digests.values()]))


def _share(episodes: Sequence[EvaluationEpisode], condition) -> float:
    return sum(1 for episode in episodes if condition(episode)) / len(episodes)
