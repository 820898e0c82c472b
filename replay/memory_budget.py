"""The replay's memory budget against its capacity: how many full-length episodes replay.memory_budget_mb
holds at a frame size (the estimate at start, the measured mean later), said in one log line, loudly when
fewer than replay.capacity."""

from __future__ import annotations

import logging
import math

from common.config import Config
from replay.store import EpisodeStore, full_episodes_fit, step_bytes

log = logging.getLogger("replay")

MEGABYTE = 1 << 20
KILOBYTE = 1 << 10


def report_budget(config: Config, store: EpisodeStore, frame_bytes: float, source: str) -> bool:
    """Whether the budget holds replay.capacity full-length episodes of frames of `frame_bytes`, logged."""
    replay, max_steps = config.replay, config.env.max_steps
    fits = full_episodes_fit(store.budget_bytes, max_steps, frame_bytes, store.state_units)
    needed_mb = math.ceil(replay.capacity * ((max_steps + 1) * frame_bytes
                                             + max_steps * step_bytes(store.state_units)) / MEGABYTE)
    if fits >= replay.capacity:
        log.info("memory budget %.0f MB holds %d episodes of env.max_steps = %d steps at %.2f KB per frame "
                 "(%s): replay.capacity %d fits", replay.memory_budget_mb, fits, max_steps,
                 frame_bytes / KILOBYTE, source, replay.capacity)
        return True
    log.warning("REPLAY.CAPACITY DOES NOT FIT: replay.memory_budget_mb %.0f holds only %d of %d episodes of "
                "env.max_steps = %d steps at %.2f KB per frame (%s); once episodes grow long the budget "
                "evicts early. Set --replay.memory_budget_mb %d (or more) to hold the configured buffer",
                replay.memory_budget_mb, fits, replay.capacity, max_steps, frame_bytes / KILOBYTE, source,
                needed_mb)
    return False
