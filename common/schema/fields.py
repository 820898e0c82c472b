"""Declaring one field of the configuration and checking its value: the pieces every config section
(common/config.py) is written with."""

from __future__ import annotations

from dataclasses import field
from typing import Any


def option(default: Any, doc: str, unit: str = "", choices: tuple[str, ...] = ()) -> Any:
    """A config field with its one documentation string, which `--help` shows: what the value
    means, its unit (if it has one) and, for a closed set of words, its choices."""
    metadata = {"doc": doc, "unit": unit, "choices": choices}
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=metadata)
    return field(default=default, metadata=metadata)


class ConfigError(ValueError):
    """A configuration value, file or flag is wrong; the message names the key."""


def check(condition: bool, key: str, message: str) -> None:
    if not condition:
        raise ConfigError(f"{key}: {message}")


def check_positive(section: Any, *names: str) -> None:
    for name in names:
        value = getattr(section, name)
        check(value > 0, name, f"must be > 0, got {value!r}")


def check_probability(section: Any, *names: str) -> None:
    for name in names:
        value = getattr(section, name)
        check(0.0 <= value <= 1.0, name, f"must lie in [0, 1], got {value!r}")
