"""The episode store: whole episodes in, random traces out (Bootstrapped Random Updates).

Episodes keep their frames compressed exactly as they arrived; a sampled trace
refers to the stored frame blobs, so overlapping traces never copy frames.
Eviction is oldest-first, bounded by an episode count and a byte budget; evictions
the budget forces below the count are counted apart, so a short buffer never goes unseen.
A store of a run with learner.stored_state keeps each episode's LSTM state rows and hands
every trace the row of its first step (common/stored_state.py); other stores drop them.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from dataclasses import dataclass

import numpy as np

from common.wire.state_rows import STATE_DTYPE, bytes_per_step, no_states
from common.wire.frames import FrameStack
from common.wire.messages import Episode, TraceBatch
from replay.buffer_fill import BufferFill


# actions (int64), rewards (float32) and weights versions (int64) of one stored step
STEP_METADATA_BYTES = 8 + 4 + 8


def full_episodes_fit(budget_bytes: int, max_steps: int, frame_bytes: float, state_units: int = 0) -> int:
    """How many episodes of max_steps steps (max_steps + 1 frames of frame_bytes) a budget holds."""
    episode_bytes = (max_steps + 1) * frame_bytes + max_steps * step_bytes(state_units)
    return int(budget_bytes // episode_bytes)


def step_bytes(state_units: int) -> int:
    """The bytes of one stored step besides its frame: actions, rewards, versions and any LSTM state."""
    return STEP_METADATA_BYTES + (bytes_per_step(state_units) if state_units else 0)


@dataclass(frozen=True)
class StoredEpisode:
    frames: FrameStack  # L + 1 observations, compressed
    actions: np.ndarray  # int64 [L]
    rewards: np.ndarray  # float32 [L]
    weights_version: np.ndarray  # int64 [L]
    terminated: bool  # the last step ended in a terminal state
    nbytes: int
    seq: int = -1  # the store's insertion number: names the episode in snapshots
    states: np.ndarray | None = None  # float16 [L, 2, lstm_units]: the LSTM state before each step, if kept

    @property
    def length(self) -> int:
        return len(self.actions)

    @classmethod
    def from_episode(cls, episode: Episode, state_units: int = 0) -> "StoredEpisode":
        """The episode as stored; its state rows are kept when they have state_units units (0: dropped)."""
        rows = np.asarray(episode.recurrent_state)
        keep = state_units > 0 and rows.shape == (len(episode.actions), 2, state_units)
        return cls.of(episode.observations, episode.actions, episode.rewards, episode.weights_version,
                      bool(episode.terminated), states=rows if keep else None)

    @classmethod
    def of(cls, frames: FrameStack, actions: np.ndarray, rewards: np.ndarray, weights_version: np.ndarray,
           terminated: bool, seq: int = -1, states: np.ndarray | None = None) -> "StoredEpisode":
        nbytes = frames.nbytes + actions.nbytes + rewards.nbytes + weights_version.nbytes
        nbytes += 0 if states is None else states.nbytes
        return cls(frames, actions, rewards, weights_version, terminated, nbytes, seq, states)


class EpisodeStore:
    """Holds up to `capacity` episodes within `budget_bytes`; samples traces uniformly."""

    def __init__(self, capacity: int, budget_bytes: int, trace_length: int, seed: int = 0,
                 state_units: int = 0) -> None:
        self.capacity = capacity
        self.state_units = state_units  # learner.stored_state: keep LSTM state rows of this many units; 0: none
        self.budget_bytes = budget_bytes
        self.trace_length = trace_length
        self._episodes: deque[StoredEpisode] = deque()
        self._rng = np.random.default_rng(seed)
        self.bytes = 0
        self.frames = 0
        self.state_bytes = 0  # of the held episodes' LSTM state rows
        self.inserted = 0
        self.evicted = 0
        self.evicted_for_budget = 0  # evictions while fewer than `capacity` episodes were held
        self.short_dropped = 0
        self.env_steps_total = 0  # every step received, stored or not: the system's step count
        self.fill = BufferFill()  # the random phase's share held and served; when the buffer first filled

    def __len__(self) -> int:
        return len(self._episodes)

    def add(self, episode: Episode) -> bool:
        """Stores the episode unless it is too short to hold one trace; evicts the oldest to fit."""
        self.env_steps_total += len(episode.actions)
        if len(episode.actions) < self.trace_length:
            self.short_dropped += 1
            return False
        self._append(dataclasses.replace(StoredEpisode.from_episode(episode, self.state_units), seq=self.inserted))
        self.inserted += 1
        self._evict_to_fit()
        self.fill.on_count(len(self._episodes), self.capacity, self.env_steps_total)
        return True

    def _append(self, stored: StoredEpisode) -> None:
        self._episodes.append(stored)
        self.bytes += stored.nbytes
        self.frames += len(stored.frames)
        self.state_bytes += 0 if stored.states is None else stored.states.nbytes
        self.fill.on_held(stored.weights_version, +1)

    def _evict_to_fit(self) -> None:
        while len(self._episodes) > self.capacity or (self.bytes > self.budget_bytes and len(self._episodes) > 1):
            if len(self._episodes) <= self.capacity:
                self.evicted_for_budget += 1
            self._evict_oldest()

    # --- snapshots --------------------------------------------------------------------------

    COUNTERS = ("inserted", "evicted", "evicted_for_budget", "short_dropped", "env_steps_total")

    def episodes(self) -> list[StoredEpisode]:
        """The stored episodes, oldest first (immutable: safe to read outside the replay's lock)."""
        return list(self._episodes)

    def counters(self) -> dict[str, int]:
        return {**{name: getattr(self, name) for name in self.COUNTERS}, **self.fill.counters()}

    def restore(self, episodes: list[StoredEpisode], counters: dict[str, int]) -> None:
        """An empty store takes a snapshot's episodes (oldest first) and counters; the newest that fit
        capacity and budget are kept."""
        if self._episodes:
            raise RuntimeError("restore into a store that holds episodes")
        for name in self.COUNTERS:
            setattr(self, name, int(counters.get(name, 0)))
        self.fill.restore(counters)
        for stored in episodes:
            self._append(self._with_usable_states(stored))
        self.inserted = max(self.inserted, max((stored.seq + 1 for stored in episodes), default=0))
        evicted = self.evicted
        self._evict_to_fit()
        self.evicted = evicted  # not evictions of this run: the config shrank

    def _with_usable_states(self, stored: StoredEpisode) -> StoredEpisode:
        """A restored episode keeps its state rows only if this store uses rows of their size."""
        if stored.states is None or stored.states.shape == (stored.length, 2, self.state_units):
            return stored
        return StoredEpisode.of(stored.frames, stored.actions, stored.rewards, stored.weights_version,
                                stored.terminated, stored.seq)

    @property
    def frame_bytes_mean(self) -> float:
        """Mean compressed size of a stored frame (nan while empty)."""
        if not self.frames:
            return float("nan")
        steps = self.frames - len(self._episodes)
        return (self.bytes - steps * STEP_METADATA_BYTES - self.state_bytes) / self.frames

    def sample(self, batch_size: int, request_id: int = 0) -> TraceBatch:
        """B traces of T steps: an episode uniformly, then a start uniformly inside it."""
        if not self._episodes:
            raise LookupError("the replay holds no episode long enough to sample")
        steps = self.trace_length
        picks = self._rng.integers(len(self._episodes), size=batch_size)
        stacks, actions, rewards, terminated, versions, states = [], [], [], [], [], []
        for pick in picks:
            episode = self._episodes[int(pick)]
            start = int(self._rng.integers(episode.length - steps + 1))
            stop = start + steps
            stacks.append(episode.frames.select(range(start, stop + 1)))
            actions.append(episode.actions[start:stop])
            rewards.append(episode.rewards[start:stop])
            versions.append(episode.weights_version[start:stop])
            ends_episode = np.zeros(steps, dtype=bool)
            ends_episode[-1] = episode.terminated and stop == episode.length
            terminated.append(ends_episode)
            if self.state_units:  # an episode kept without rows (restored from another run) starts from zero
                states.append(episode.states[start] if episode.states is not None
                              else np.zeros((2, self.state_units), STATE_DTYPE))
        self.fill.on_sample(np.stack(versions))
        return TraceBatch(
            request_id=request_id,
            observations=FrameStack.concat(stacks),
            actions=np.stack(actions).astype(np.int64),
            rewards=np.stack(rewards).astype(np.float32),
            terminated=np.stack(terminated),
            weights_version=np.stack(versions).astype(np.int64),
            env_steps_total=self.env_steps_total,
            episodes_stored=len(self._episodes),
            initial_state=np.stack(states) if states else no_states(),
        )

    def _evict_oldest(self) -> None:
        oldest = self._episodes.popleft()
        self.bytes -= oldest.nbytes
        self.frames -= len(oldest.frames)
        self.state_bytes -= 0 if oldest.states is None else oldest.states.nbytes
        self.fill.on_held(oldest.weights_version, -1)
        self.evicted += 1
