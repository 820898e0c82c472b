"""Statistics of an evaluation: per-episode records in, the rows of the paper's tables out.

Pure functions over plain records, so every figure can be checked by hand.
Conventions (the paper does not spell them out):

* CFR (collision-free rate) is the share of episodes that reach the step cap
  without a collision. An episode that leaves the road before the cap is not
  collision-free in this sense: it did not reach the cap.
* The standard deviation of episode lengths is the population one (ddof = 0,
  numpy's default).
* Mean reward per step and the reward-bin shares pool every step of every
  episode of the group (an episode of 2,000 steps weighs 2,000 times one of a
  single step), as the paper's figure of step-reward shares does.
* Reward bins are half-open [a, b) except the last, which is closed [a, b], so
  a reward of exactly 1 (the car on the centre-line) falls in the top bin.
"""

from __future__ import annotations

import hashlib
from collections import defaultdict
from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

END_REASONS = ("collision", "offroad", "cap")


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

    @property
    def collision_free(self) -> bool:
        return self.end == "cap"


@dataclass(frozen=True)
class SetSummary:
    """One table row: one policy on one start set."""

    policy: str
    start_set: str
    episodes: int
    mean_length: float
    std_length: float
    min_length: int
    max_length: int
    cfr: float  # share of episodes reaching the cap without a collision
    collision_share: float  # share of episodes ended by a collision
    offroad_share: float  # share of episodes ended by leaving the road
    mean_reward_per_step: float
    reward_shares: tuple[float, ...]  # share of all steps whose reward fell in each bin
    distinct_per_start: float  # distinct trajectories among the trials of a start, averaged over starts


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


def summarise(episodes: Sequence[EvaluationEpisode]) -> SetSummary:
    """The row of one group of episodes that share a policy and a start set."""
    if not episodes:
        raise ValueError("cannot summarise an empty group of episodes")
    groups = {(episode.policy, episode.start_set) for episode in episodes}
    if len(groups) != 1:
        raise ValueError(f"a summary row needs one policy and one start set, got {sorted(groups)}")
    lengths = np.array([episode.length for episode in episodes], dtype=np.float64)
    steps = lengths.sum()
    bin_totals = np.sum([episode.reward_bin_counts for episode in episodes], axis=0)
    policy, start_set = groups.pop()
    return SetSummary(
        policy=policy,
        start_set=start_set,
        episodes=len(episodes),
        mean_length=float(lengths.mean()),
        std_length=float(lengths.std()),
        min_length=int(lengths.min()),
        max_length=int(lengths.max()),
        cfr=_share(episodes, lambda episode: episode.collision_free),
        collision_share=_share(episodes, lambda episode: episode.end == "collision"),
        offroad_share=_share(episodes, lambda episode: episode.end == "offroad"),
        mean_reward_per_step=float(sum(episode.episode_return for episode in episodes) / steps),
        reward_shares=tuple(float(count / steps) for count in bin_totals),
        distinct_per_start=distinct_trajectories_per_start(episodes),
    )


def summarise_all(episodes: Iterable[EvaluationEpisode]) -> list[SetSummary]:
    """One row per (policy, start set), in the order the groups first appear."""
    groups: dict[tuple[str, str], list[EvaluationEpisode]] = defaultdict(list)
    for episode in episodes:
        groups[(episode.policy, episode.start_set)].append(episode)
    return [summarise(group) for group in groups.values()]


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
