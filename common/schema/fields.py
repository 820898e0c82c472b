"""Declaring one field of the configuration, checking its value and converting one given as text: the pieces
every config section (common/config.py, and the strategies' in common/exploration/) is written with."""

from __future__ import annotations

import math
import typing
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


def field_types(instance: Any) -> dict[str, Any]:
    """The declared type of each field of a config section (a dataclass instance)."""
    return typing.get_type_hints(type(instance))


def coerce(key: str, kind: Any, value: Any) -> Any:
    """`value` as a field of type `kind` holds it (a flag's or TOML's string converted), or ConfigError naming `key`."""
    origin = typing.get_origin(kind)
    if origin is list:
        (item_kind,) = typing.get_args(kind)
        if isinstance(value, str):
            value = [part for part in (p.strip() for p in value.split(",")) if part]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        return [coerce(key, item_kind, item) for item in value]
    if kind is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "1", "yes", "on", "false", "0", "no", "off"):
            return value.lower() in ("true", "1", "yes", "on")
        raise ConfigError(f"{key}: expected true or false, got {value!r}")
    if kind is int:
        if isinstance(value, bool):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        if isinstance(value, int):
            return value
        if isinstance(value, str):
            try:
                return int(value.replace("_", ""))
            except ValueError:
                pass
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise ConfigError(f"{key}: expected an integer, got {value!r}")
    if kind is float:
        if isinstance(value, bool):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{key}: expected a number, got {value!r}") from None
        if not math.isfinite(number):
            raise ConfigError(f"{key}: expected a finite number, got {value!r}")
        return number
    if kind is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return value
    raise ConfigError(f"{key}: unsupported field type {kind!r}")
