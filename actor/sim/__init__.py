"""The driving simulator: a small urban neighbourhood on highway-env, seen through a front camera.

``make_env(config.env, seed)`` is what the actor and the evaluator call; the
environment is also registered with gymnasium as ``d3rqn/Neighbourhood-v0``.
"""

from __future__ import annotations

import gymnasium

from actor.sim.env import START_SETS, STEERING_LEVELS, NeighbourhoodEnv
from actor.sim.neighbourhood import Pose, neighbourhood
from common.sim_config import EnvConfig

ENV_ID = "d3rqn/Neighbourhood-v0"

if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point="actor.sim.env:NeighbourhoodEnv")


def make_env(env_config: EnvConfig, seed: int | None = None) -> gymnasium.Env:
    """A new simulator; with ``seed``, its start draws and action-space samples are seeded."""
    env = gymnasium.make(ENV_ID, env_config=env_config, disable_env_checker=True)
    if seed is not None:
        env.reset(seed=seed)
        env.action_space.seed(seed)
    return env


def start_poses(start_set: str) -> tuple[Pose, ...]:
    """The fixed start poses of a set ("train" or "test"), indexed as ``start_index``."""
    return neighbourhood().start_poses[start_set]


__all__ = ["ENV_ID", "START_SETS", "STEERING_LEVELS", "NeighbourhoodEnv", "Pose", "make_env",
           "start_poses"]
