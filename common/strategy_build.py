"""A strategy built by name: from the config's exploration section (``make_strategy``), or from another
process's state (``strategy_from_state``: the learner is the authority; the full config checks every
value), and its state as the wire message the actors load."""

from __future__ import annotations

import dataclasses

from common.config import Config, ExplorationConfig
from common.config_values import set_value
from common.exploration.base import ExplorationStrategy
from common.exploration.bmc import EpsilonBmc
from common.exploration.boltzmann import MaxBoltzmann, Softmax
from common.exploration.epsilon_greedy import ConstantEpsilonGreedy, DecreasingEpsilonGreedy
from common.exploration.names import strategy_named
from common.exploration.vdbe import Vdbe, VdbeSoftmax
from common.schema.fields import ConfigError
from common.wire.messages import ExplorationState


# One class per name of common/exploration/names.py, built from that name's config sections.
STRATEGY_CLASSES = {cls.name: cls for cls in (ConstantEpsilonGreedy, DecreasingEpsilonGreedy, Vdbe, EpsilonBmc,
                                              Softmax, MaxBoltzmann, VdbeSoftmax)}


def make_strategy(config: ExplorationConfig, n_actions: int) -> ExplorationStrategy:
    """The strategy named by config.strategy, with its sections of the config."""
    sections = strategy_named(config.strategy).sections
    return STRATEGY_CLASSES[config.strategy](n_actions, *(getattr(config, section) for section in sections))


def same_strategy(strategy: ExplorationStrategy, state: dict) -> bool:
    """Whether a state_dict() describes this strategy with these params."""
    return state.get("strategy") == strategy.name and state.get("params") == strategy.params()


def strategy_from_state(state: dict, n_actions: int) -> ExplorationStrategy:
    """The strategy another process's state_dict() describes, built from its name and params
    (not from the local config) and loaded with its state; ValueError if it cannot be."""
    try:
        name, params = state["strategy"], state["params"]
        sections = strategy_named(name).sections
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"exploration state names no known strategy ({str(state)[:200]})") from None
    if not isinstance(params, dict):
        raise ValueError(f"exploration params must be a map, got {params!r}")
    config = Config()
    config.exploration.strategy = name
    owners = {f.name: section for section in sections
              for f in dataclasses.fields(getattr(config.exploration, section))}
    try:
        for key, value in params.items():
            if key not in owners:
                raise ValueError(f"exploration param {key!r} is not one of {name}'s ({', '.join(sorted(owners))})")
            set_value(config, f"exploration.{owners[key]}.{key}", value)
        for section in sections:
            getattr(config.exploration, section).validate()
    except ConfigError as error:
        raise ValueError(f"exploration params: {error}") from None
    strategy = make_strategy(config.exploration, n_actions)
    strategy.load_state_dict(state)
    return strategy


def exploration_message(strategy: ExplorationStrategy, start_by_steps: bool | None = None) -> ExplorationState:
    """The strategy's state_dict() as the wire message the actors load, with the learner's start rule
    for the replay (common/wire/messages.py)."""
    return ExplorationState(**strategy.state_dict(), start_by_steps=start_by_steps)
