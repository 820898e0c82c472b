"""A strategy built by name from the registry (names.py), with its config sections: from the config's
exploration section (``make_strategy``), or from another process's params (``sections_from_params``, then
``strategy_from``: the learner is the authority, and each section's own checks hold every value)."""

from __future__ import annotations

import dataclasses
from typing import Any

from common.exploration.base import ExplorationStrategy, record
from common.exploration.names import SECTIONS, strategy_named


def make_strategy(config: Any, n_actions: int) -> ExplorationStrategy:
    """The strategy named by config.strategy, with its sections of the config (config: the exploration
    section of common/config.py, which this folder cannot import: the config is written with these modules)."""
    sections = tuple(getattr(config, section) for section in strategy_named(config.strategy).sections)
    return strategy_from(config.strategy, sections, n_actions)


def strategy_from(name: str, sections: tuple, n_actions: int) -> ExplorationStrategy:
    """The strategy of this name built with these config sections, in its class's order (as
    ``sections_from_params`` reads them), before any state: not started, counters at 0."""
    entry = strategy_named(name)
    if tuple(type(section) for section in sections) != tuple(SECTIONS[section] for section in entry.sections):
        raise ValueError(f"{name} is built with sections {', '.join(entry.sections)}, got "
                         f"{', '.join(type(section).__name__ for section in sections)}")
    return entry.cls(n_actions, *sections)


def sections_from_params(name: str, params: Any) -> tuple:
    """The config sections of strategy `name` from its params as one map (ExplorationStrategy.params(), the
    form the wire and checkpoints write): each param on the section that declares it, one absent at its
    default (a writer older than the param), every section checked. ValueError for an unknown name or param."""
    entry = strategy_named(name)
    if not isinstance(params, dict):
        raise ValueError(f"exploration params must be a map, got {type(params).__name__}")
    owners = {f.name: section for section in entry.sections for f in dataclasses.fields(SECTIONS[section])}
    unknown = sorted(str(key) for key in params if key not in owners)
    if unknown:
        raise ValueError(f"exploration param(s) {', '.join(unknown)} not among {name}'s ({', '.join(sorted(owners))})")
    return tuple(record(SECTIONS[section], {key: value for key, value in params.items() if owners[key] == section},
                        f"exploration.{section}") for section in entry.sections)
