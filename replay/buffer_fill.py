"""What the buffer holds and serves of the random phase, and when it first filled.

A run's buffer may never fill: a 2,000-episode buffer at 13% of the paper's budget holds every
episode the run took. Then "a larger buffer" only means "the random phase's episodes are never
dropped", and these counters say how much of the learner's diet they still are.

A step is of the random phase when it was acted before the actor held trained weights: its
weights version is 0 (the initial network) or -1 (none yet). The sample counters count from the
first batch this store's counters remember (`sampled_batches` says how many that is).
"""

from __future__ import annotations

import logging

import numpy as np

from common.wire.messages import BufferFillState

log = logging.getLogger(__name__)

UNTRAINED_VERSION = 0  # weights versions at or below this were acted without trained weights


def random_steps(weights_version: np.ndarray) -> int:
    """How many of the steps were acted without trained weights."""
    return int(np.count_nonzero(np.asarray(weights_version) <= UNTRAINED_VERSION))


class BufferFill:
    """Counters of the random phase's share in what the store holds and serves, and of its first fill."""

    COUNTERS = ("sampled_batches", "sampled_steps", "sampled_random_steps", "full_at_env_steps",
                "full_at_batches", "sampled_steps_after_full", "sampled_random_steps_after_full")

    def __init__(self) -> None:
        self.held_random_steps = 0  # recounted from the episodes on restore, so not among COUNTERS
        self.sampled_batches = 0
        self.sampled_steps = 0
        self.sampled_random_steps = 0
        self.full_at_env_steps = 0  # 0: never full
        self.full_at_batches = 0
        self.sampled_steps_after_full = 0
        self.sampled_random_steps_after_full = 0

    @property
    def filled(self) -> bool:
        return self.full_at_env_steps > 0

    def on_held(self, weights_version: np.ndarray, sign: int) -> None:
        """An episode came in (+1) or went out (-1)."""
        self.held_random_steps += sign * random_steps(weights_version)

    def on_count(self, held: int, capacity: int, env_steps: int) -> bool:
        """The store holds `held` episodes after an insertion; True the first time that is its capacity."""
        if self.filled or held < capacity:
            return False
        self.full_at_env_steps, self.full_at_batches = max(1, env_steps), self.sampled_batches
        log.info("the buffer is full: %d episodes at %d env steps, after %d batches; the oldest go from here",
                 held, env_steps, self.sampled_batches)
        return True

    def on_sample(self, weights_version: np.ndarray) -> None:
        """A batch went out with these steps' weights versions ([B, T])."""
        steps, random = int(np.size(weights_version)), random_steps(weights_version)
        self.sampled_batches += 1
        self.sampled_steps += steps
        self.sampled_random_steps += random
        if self.filled:
            self.sampled_steps_after_full += steps
            self.sampled_random_steps_after_full += random

    def state(self) -> BufferFillState:
        return BufferFillState(held_random_steps=self.held_random_steps, **self.counters())

    def counters(self) -> dict[str, int]:
        return {name: getattr(self, name) for name in self.COUNTERS}

    def restore(self, counters: dict) -> None:
        """A snapshot's counters; those it lacks (a snapshot from before these counters) start at 0."""
        for name in self.COUNTERS:
            value = counters.get(name, 0)
            setattr(self, name, value if isinstance(value, int) and value >= 0 else 0)
