"""A config's values by dotted key: built from a preset, a TOML file and overrides (``load_config``), set
one key at a time with its type checked (``set_value``), read back (``flat_items``, ``config_fields``),
written as TOML (``to_toml``) and as a table for checkpoints (``to_dict``, ``from_dict``).
"""

from __future__ import annotations

import copy
import dataclasses
import tomllib
from pathlib import Path
from typing import Any

from common.config import Config, sections
from common.schema.fields import ConfigError, coerce, field_types
from common.presets import PRESETS


def load_config(preset: str = "paper", toml_path: str | Path | None = None,
                overrides: dict[str, Any] | None = None, base: Config | None = None) -> Config:
    """Preset (or a copy of `base`, such as a checkpoint's config), then TOML file, then
    overrides (dotted keys); validated."""
    if base is not None:
        config = copy.deepcopy(base)
    elif preset in PRESETS:
        config = Config()
        for key, value in PRESETS[preset].items():
            set_value(config, key, value)
    else:
        raise ConfigError(f"preset: unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    if toml_path is not None:
        for key, value in _flatten(_read_toml(Path(toml_path))).items():
            set_value(config, key, value)
    for key, value in (overrides or {}).items():
        set_value(config, key, value)
    return config.validate()


# Keys of earlier versions; a checkpoint's or log's config that holds one still loads (from_dict).
RETIRED_KEYS = {
    "learner.ratio_tolerance": "replaced by pace.error_buffer_updates (a number of updates)",
    "actor.pace_with_learner": "the replay's rate limiter paces the actors; pace.error_buffer_updates 1e9 lets them run free",
}


# Keys that moved to another section: a run folder's, checkpoint's or user's config that holds one still loads.
MOVED_KEYS = {
    **{f"learner.{name}": f"pace.{name}" for name in
       ("env_steps_per_update", "start_episodes", "start_steps", "start_by", "total_env_steps")},
    **{f"replay.{name}": f"pace.{name}" for name in ("error_buffer_updates", "hold_updates")},
    **{f"record.{name}": f"recorder.{name}" for name in
       ("enabled", "weights_every_versions", "flush_period_s", "chunk_mb", "queue_messages", "queue_mb", "views",
        "images", "image_format", "stats_period_s")},
}


def set_value(config: Config, dotted_key: str, value: Any) -> None:
    """Set one field by its dotted path (a moved key by its new one), converting and type-checking the value."""
    if dotted_key in RETIRED_KEYS:
        raise ConfigError(f"{dotted_key}: retired key; {RETIRED_KEYS[dotted_key]}")
    dotted_key = MOVED_KEYS.get(dotted_key, dotted_key)
    *parents, name = dotted_key.split(".")
    target: Any = config
    for part in parents:
        if not dataclasses.is_dataclass(target) or part not in field_types(target):
            raise ConfigError(f"{dotted_key}: unknown key")
        target = getattr(target, part)
    types = field_types(target) if dataclasses.is_dataclass(target) else {}
    if name not in types or dataclasses.is_dataclass(types[name]):
        raise ConfigError(f"{dotted_key}: unknown key")
    setattr(target, name, coerce(dotted_key, types[name], value))


def flat_items(config: Any, prefix: str = "") -> dict[str, Any]:
    """Every leaf field as {dotted key: value}."""
    items: dict[str, Any] = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        key = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            items.update(flat_items(value, key + "."))
        else:
            items[key] = value
    return items


def to_toml(config: Config) -> str:
    """The config as a TOML document that load_config reads back unchanged."""
    lines: list[str] = []
    for path, section in sections(config):
        leaves = {f.name: getattr(section, f.name) for f in dataclasses.fields(section)
                  if not dataclasses.is_dataclass(getattr(section, f.name))}
        if not path or not leaves:
            continue
        lines.append(f"[{path}]")
        lines.extend(f"{name} = {toml_value(value)}" for name, value in leaves.items())
        lines.append("")
    return "\n".join(lines)


def from_dict(nested: dict[str, Any]) -> Config:
    """A config from the nested dict of a TOML document or a checkpoint."""
    config = Config()
    for key, value in _flatten(nested).items():
        if key not in RETIRED_KEYS:
            set_value(config, key, value)
    return config.validate()


def to_dict(config: Config) -> dict[str, Any]:
    return dataclasses.asdict(config)


def config_fields() -> dict[str, dataclasses.Field]:
    """Every leaf field by dotted key; its metadata holds the doc, unit and choices of option()."""
    fields: dict[str, dataclasses.Field] = {}
    for path, section in sections(Config()):
        for f in dataclasses.fields(section):
            if not dataclasses.is_dataclass(getattr(section, f.name)):
                fields[f"{path}.{f.name}" if path else f.name] = f
    return fields


def _flatten(nested: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in nested.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        with path.open("rb") as handle:
            return tomllib.load(handle)
    except FileNotFoundError:
        raise ConfigError(f"config file {path}: not found") from None
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"config file {path}: invalid TOML ({error})") from None


def toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(item) for item in value) + "]"
    raise TypeError(f"cannot write {value!r} as TOML")
