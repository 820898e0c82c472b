"""The pace of a run, as pure arithmetic the replay's rate limiter (replay/rate_limiter.py), the learner
(learner/service.py) and the reference loop (deploy/reference_loop.py) share: the settings of the one
ratio of env steps to updates, where updates start (the start mark), the updates the steps since then
pay for, the ratio achieved, and whether the error buffer paces anybody at all.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from common.exploration.names import starts_by_steps


@dataclass(frozen=True)
class RateLimit:
    """The limiter's settings, from pace.env_steps_per_update, pace.start_episodes,
    pace.start_steps, pace.total_env_steps, pace.error_buffer_updates and pace.hold_updates."""

    env_steps_per_update: float
    start_episodes: int
    start_steps: int
    error_buffer: float  # B, in updates: how far the learner may run ahead
    total_env_steps: int | None = None  # actors hold for good once this many steps arrived
    start_by_steps: bool = False  # decreasing epsilon: start at start_steps, not start_episodes
    hold_buffer: float = 0.0  # H, in updates: how far the learner may fall behind before actors hold, if more than B

    def __post_init__(self) -> None:
        if not self.env_steps_per_update > 0:
            raise ValueError(f"env_steps_per_update must be > 0, got {self.env_steps_per_update}")
        if self.start_episodes < 1 or self.start_steps < 0:
            raise ValueError(f"start_episodes must be >= 1 and start_steps >= 0, got "
                             f"{self.start_episodes} and {self.start_steps}")
        if not self.error_buffer >= 1:  # Reverb: narrower buffers can block both sides
            raise ValueError(f"error_buffer must be >= 1 update, got {self.error_buffer}")
        if not self.hold_buffer >= 0:
            raise ValueError(f"hold_buffer must be >= 0 updates, got {self.hold_buffer}")

    @property
    def actors_lead(self) -> float:
        """The updates the learner may fall behind before actors hold their next episode: H, but never
        less than B, so that a buffer that holds nobody (an unpaced run) holds the actors neither."""
        return max(self.hold_buffer, self.error_buffer)


def rate_limit_from_config(config, strategy: str | None = None) -> RateLimit:
    """The RateLimit of a Config; `strategy` (the learner's, when known) picks the start rule."""
    pace = config.pace
    return RateLimit(
        env_steps_per_update=pace.env_steps_per_update,
        start_episodes=pace.start_episodes,
        start_steps=pace.start_steps,
        error_buffer=pace.error_buffer_updates,
        hold_buffer=pace.hold_updates,
        total_env_steps=pace.total_env_steps,
        start_by_steps=starts_by_steps(strategy or config.exploration.strategy, pace.start_by),
    )


def learner_stock(prefetch: int) -> int:
    """The most batches a running learner (learner/prefetch.py, `prefetch` workers) can have been served
    and not updated on when its request reaches the replay: `prefetch` queued, one per worker in
    transit or in hand, one in the update, and one per other worker whose next request overtook this one."""
    return 3 * prefetch + 1


def start_mark_of(limit: RateLimit, steps_before: int, steps_after: int, episodes_stored: int) -> float | None:
    """The start mark an episode sets, if it starts the updates: it took the run from steps_before to
    steps_after env steps and left episodes_stored episodes in the store. By episodes, the mark is the
    steps so far; by steps, exactly start_steps (the crossing episode's later steps are owed already)."""
    if limit.start_by_steps:
        return float(max(steps_before, limit.start_steps)) if steps_after >= limit.start_steps else None
    return float(steps_after) if episodes_stored >= limit.start_episodes else None


def updates_paid_for(env_steps: float, start_mark: float, env_steps_per_update: float) -> float:
    """The updates the env steps since the start mark pay for: (env_steps - start_mark) / env_steps_per_update."""
    return (env_steps - start_mark) / env_steps_per_update


def achieved_ratio(env_steps: float, start_mark: float | None, updates: int) -> float:
    """The env steps since the start mark per update made (nan before the start or the first update)."""
    if start_mark is None or updates <= 0:
        return math.nan
    return (env_steps - start_mark) / updates


def is_unpaced(error_buffer: float, total_env_steps: int | None, env_steps_per_update: float) -> bool:
    """Whether the error buffer holds nobody: it is at least the updates the whole budget pays for."""
    return total_env_steps is not None and error_buffer >= total_env_steps / env_steps_per_update


def env_steps_ceiling(config) -> int:
    """More env steps than this no run of the config can count: actors are held once the budget is spent,
    and what is still in flight then is less than a full buffer of full-length episodes. Counts above it
    come from no replay of this run, and the roles refuse them."""
    return config.pace.total_env_steps + config.replay.capacity * config.env.max_steps


def updates_ceiling(config) -> int:
    """More updates than this no learner of the config makes: what the most env steps it can count
    (env_steps_ceiling) pay for from a start mark of 0, plus its error buffer. Claims above it are refused."""
    return math.ceil(updates_paid_for(env_steps_ceiling(config), 0.0, config.pace.env_steps_per_update)
                     + config.pace.error_buffer_updates)
