"""The command line of a config: one flag per field, named after its dotted key (``--learner.lr 3e-4``),
over ``--preset`` and ``--config FILE.toml``. ``--preset NAME --help`` shows that preset's defaults.
Flags are never abbreviated: an unknown one is an error that suggests the nearest known flag.
"""

from __future__ import annotations

import argparse
import difflib
import sys
import textwrap
from typing import Any

from common.config import Config
from common.config_values import MOVED_KEYS, config_fields, flat_items, load_config, to_toml, toml_value
from common.schema.fields import ConfigError
from common.presets import PRESETS, Preset




def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """Adds --preset, --config, --dump-config and one flag per config field, whose help is the
    field's documentation with the defaults of the preset given before --help."""
    parser.allow_abbrev = False  # a mistyped prefix (--run.nam) must not set another key
    _shorten_usage(parser)
    flags: dict[str, argparse.Action] = {}
    parser.add_argument("--preset", default="paper", choices=sorted(PRESETS), action=_PresetAction, flags=flags,
                        help="base values, listed below (default: paper); `--preset NAME --help` shows its defaults")
    parser.add_argument("--config", metavar="FILE.toml", help="TOML file applied over the preset")
    parser.add_argument("--dump-config", action="store_true", help="print the resolved config as TOML and exit")
    for name, preset in PRESETS.items():
        parser.add_argument_group(f"preset {name}", _preset_description(preset))
    group = parser.add_argument_group("configuration (dotted keys; applied over preset and file)")
    defaults = flat_items(Config())
    for key, f in config_fields().items():
        choices = f.metadata["choices"]
        metavar = "{" + ",".join(choices) + "}" if choices else _metavar(defaults[key])
        flags[key] = group.add_argument(f"--{key}", dest=_dest(key), default=None, metavar=metavar)
    for old, key in MOVED_KEYS.items():  # an earlier version's flag still works, unlisted
        parser.add_argument(f"--{old}", dest=_dest(key), default=None, help=argparse.SUPPRESS)
    _show_defaults(flags, "paper")


def parse_flags(parser: argparse.ArgumentParser, argv: list[str] | None = None) -> argparse.Namespace:
    """parser.parse_args(argv), but the error for an unknown flag suggests the nearest known one."""
    args, unknown = parser.parse_known_args(argv)
    if unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}{_suggestions(parser, unknown)}")
    return args


def config_from_args(args: argparse.Namespace, base: Config | None = None) -> Config:
    """The flags of add_config_arguments applied over the preset, or over `base` if given."""
    overrides = {key: getattr(args, _dest(key)) for key in flat_items(Config())
                 if getattr(args, _dest(key), None) is not None}
    return load_config(args.preset, args.config, overrides, base)


def parse_config_or_exit(parser: argparse.ArgumentParser, argv: list[str] | None = None
                         ) -> tuple[argparse.Namespace, Config]:
    """Parses argv; a config error is one line on stderr and exit code 2, not a traceback.

    With --dump-config, prints the TOML and exits 0.
    """
    args = parse_flags(parser, argv)
    try:
        config = config_from_args(args)
    except ConfigError as error:
        print(f"{parser.prog}: config error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    if args.dump_config:
        print(to_toml(config), end="")
        raise SystemExit(0)
    return args, config


def print_config(prog: str, config: Config) -> None:
    """The resolved config on stderr, so every process's log starts with what it ran with."""
    body = "\n".join(f"  {line}" for line in to_toml(config).splitlines() if line)
    print(f"{prog}: resolved config\n{body}", file=sys.stderr, flush=True)


def _shorten_usage(parser: argparse.ArgumentParser) -> None:
    """One placeholder for the config flags in the usage line: a hundred would bury an error message."""
    if parser.usage is None:
        own = parser.format_usage().removeprefix("usage: ").rstrip().replace("%", "%%")
        indent = " " * len(f"usage: {parser.prog} ")
        parser.usage = f"{own}\n{indent}[--preset NAME] [--config FILE.toml] [--dump-config] [--SECTION.KEY VALUE ...]"


class _PresetAction(argparse.Action):
    """Stores --preset and shows its defaults in the help of the config flags."""

    def __init__(self, option_strings: list[str], dest: str, flags: dict[str, argparse.Action], **kwargs: Any) -> None:
        super().__init__(option_strings, dest, **kwargs)
        self.flags = flags

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        setattr(namespace, self.dest, values)
        _show_defaults(self.flags, values)


def _show_defaults(flags: dict[str, argparse.Action], preset: str) -> None:
    defaults = flat_items(load_config(preset))
    fields = config_fields()
    for key, flag in flags.items():
        f = fields[key]
        unit = f" [{f.metadata['unit']}]" if f.metadata["unit"] else ""
        source = f" of preset {preset}" if key in PRESETS[preset] else ""
        text = f"{f.metadata['doc']}{unit} (default{source}: {toml_value(defaults[key])})"
        flag.help = text.replace("%", "%%")  # argparse expands %-formats in help


def _preset_description(preset: Preset) -> str:
    changes = ", ".join(f"{key} = {toml_value(value)}" for key, value in preset.items())
    text = f"{preset.doc}; sets {changes}" if changes else f"{preset.doc}"
    return textwrap.fill(text, width=100)  # pre-wrapped for parsers with a raw description formatter


def _suggestions(parser: argparse.ArgumentParser, unknown: list[str]) -> str:
    # argparse lists a parser's own flags only in this attribute; the config flags may sit in a subparser
    known = [f"--{key}" for key in config_fields()] + list(parser._option_string_actions)
    hints = []
    for token in unknown:
        flag = token.split("=", 1)[0]
        if flag.startswith("--"):
            hints += [f"; {flag}: did you mean {match}?" for match in difflib.get_close_matches(flag, known, n=1)]
    return "".join(hints)


def _dest(key: str) -> str:
    return "cfg__" + key.replace(".", "__")


def _metavar(default: Any) -> str:
    if isinstance(default, bool):
        return "BOOL"
    if isinstance(default, int):
        return "INT"
    if isinstance(default, float):
        return "FLOAT"
    if isinstance(default, list):
        return "A,B,..."
    return "STR"
