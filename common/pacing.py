"""The pace of a run, as pure arithmetic the replay's rate limiter (replay/rate_limiter.py), the learner
(learner/service.py) and the reference loop (learner/reference_loop.py) share: the settings of the
one ratio of env steps to updates.
"""

from __future__ import annotations

from dataclasses import dataclass

from common.exploration.names import starts_by_steps


@dataclass(frozen=True)
class RateLimit:
    """The limiter's settings, from learner.env_steps_per_update, learner.start_episodes,
    learner.start_steps, learner.total_env_steps and replay.error_buffer_updates."""

    env_steps_per_update: float
    start_episodes: int
    start_steps: int
    error_buffer: float  # B, in updates
    total_env_steps: int | None = None  # actors hold for good once this many steps arrived
    start_by_steps: bool = False  # decreasing epsilon: start at start_steps, not start_episodes

    def __post_init__(self) -> None:
        if not self.env_steps_per_update > 0:
            raise ValueError(f"env_steps_per_update must be > 0, got {self.env_steps_per_update}")
        if self.start_episodes < 1 or self.start_steps < 0:
            raise ValueError(f"start_episodes must be >= 1 and start_steps >= 0, got "
                             f"{self.start_episodes} and {self.start_steps}")
        if not self.error_buffer >= 1:  # Reverb: narrower buffers can block both sides
            raise ValueError(f"error_buffer must be >= 1 update, got {self.error_buffer}")


def rate_limit_from_config(config, strategy: str | None = None) -> RateLimit:
    """The RateLimit of a Config; `strategy` (the learner's, when known) picks the start rule."""
    learner = config.learner
    return RateLimit(
        env_steps_per_update=learner.env_steps_per_update,
        start_episodes=learner.start_episodes,
        start_steps=learner.start_steps,
        error_buffer=config.replay.error_buffer_updates,
        total_env_steps=learner.total_env_steps,
        start_by_steps=starts_by_steps(strategy or config.exploration.strategy, learner.start_by),
    )
