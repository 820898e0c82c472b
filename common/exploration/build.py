"""A strategy built by name from the registry (names.py): from the config's exploration section
(``make_strategy``), or from another process's state (``strategy_from_state``: the learner is the authority;
each section's own checks hold every value), and its state as the wire message the actors load."""

from __future__ import annotations

import dataclasses
from typing import Any

from common.exploration.base import ExplorationStrategy
from common.exploration.names import SECTIONS, strategy_named
from common.schema.fields import ConfigError, coerce, field_types
from common.wire.messages import ExplorationState


def make_strategy(config: Any, n_actions: int) -> ExplorationStrategy:
    """The strategy named by config.strategy, with its sections of the config (config: the exploration
    section of common/config.py, which this folder cannot import: the config is written with these modules)."""
    entry = strategy_named(config.strategy)
    return entry.cls(n_actions, *(getattr(config, section) for section in entry.sections))


def same_strategy(strategy: ExplorationStrategy, state: dict) -> bool:
    """Whether a state_dict() describes this strategy with these params."""
    return state.get("strategy") == strategy.name and state.get("params") == strategy.params()


def strategy_from_state(state: dict, n_actions: int) -> ExplorationStrategy:
    """The strategy another process's state_dict() describes, built from its name and params
    (not from the local config) and loaded with its state; ValueError if it cannot be."""
    try:
        name, params = state["strategy"], state["params"]
        entry = strategy_named(name)
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"exploration state names no known strategy ({str(state)[:200]})") from None
    if not isinstance(params, dict):
        raise ValueError(f"exploration params must be a map, got {params!r}")
    sections = {section: SECTIONS[section]() for section in entry.sections}
    try:
        _fill(sections, params, name)
    except ConfigError as error:
        raise ValueError(f"exploration params: {error}") from None
    strategy = entry.cls(n_actions, *sections.values())
    strategy.load_state_dict(state)
    return strategy


def _fill(sections: dict[str, Any], params: dict, name: str) -> None:
    """Each param set on the section that declares it, type-checked, then every section's checks."""
    owners = {f.name: section for section, values in sections.items() for f in dataclasses.fields(values)}
    for key, value in params.items():
        if key not in owners:
            raise ValueError(f"exploration param {key!r} is not one of {name}'s ({', '.join(sorted(owners))})")
        values = sections[owners[key]]
        setattr(values, key, coerce(f"exploration.{owners[key]}.{key}", field_types(values)[key], value))
    for values in sections.values():
        values.validate()


def exploration_message(strategy: ExplorationStrategy, start_by_steps: bool | None = None) -> ExplorationState:
    """The strategy's state_dict() as the wire message the actors load, with the learner's start rule
    for the replay (common/wire/messages.py)."""
    return ExplorationState(**strategy.state_dict(), start_by_steps=start_by_steps)
