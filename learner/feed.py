"""Feeding the exploration strategy after each update, what the learner knows and the strategy asks for:
the env steps of the whole system (decreasing epsilon), Q before and after the update (VDBE), and BMC's
returns at the rate of exploration.bmc.observations. The learner service (learner/service.py) and the
reference loop (deploy/reference_loop.py) both feed it here.
"""

from __future__ import annotations

import numpy as np

from common.config import Config
from common.exploration.base import ExplorationStrategy
from common.exploration.bmc import bmc_observation_count, newest_transitions
from learner.update import UpdateResult


def feed_strategy(strategy: ExplorationStrategy, result: UpdateResult, env_steps: int, config: Config) -> int:
    """Calls the strategy's hooks after one update; returns how many transitions BMC observed (0 for
    a strategy that observes none)."""
    strategy.on_env_steps(env_steps)
    if strategy.needs_q_after:
        strategy.on_update(result.q_before, result.q_after)
    if not strategy.needs_returns:
        return 0
    g_greedy, g_uniform = bmc_returns(result, config)
    strategy.on_returns(g_greedy, g_uniform)
    return int(np.size(g_greedy))


def bmc_returns(result: UpdateResult, config: Config) -> tuple[np.ndarray, np.ndarray]:
    """BMC's observations of one update: "per_step" feeds as many transitions as the update's env steps, the
    newest of each trace first (the authors' rate); "per_transition" every unmasked one."""
    if config.exploration.bmc.observations == "per_transition":
        return result.g_greedy, result.g_uniform
    count = bmc_observation_count(result.update, config.pace.env_steps_per_update)
    return newest_transitions(result.g_greedy, result.g_uniform, count)
