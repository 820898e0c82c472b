"""`replay`: the replay service. Stores actors' episodes and serves batches of random traces."""

from __future__ import annotations

import argparse

from common.config import add_config_arguments, parse_config_or_exit, print_config


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="replay",
        description="Replay service: subscribes to episodes on <namespace>/<run>/episodes, stores up to "
                    "replay.capacity of them (oldest evicted first, within replay.memory_budget_mb), answers "
                    "trace-batch queries on <namespace>/<run>/replay/sample and publishes stats.")
    add_config_arguments(parser)
    return parser


def main(argv: list[str] | None = None) -> None:
    _, config = parse_config_or_exit(build_parser(), argv)
    print_config("replay", config)
    from replay.service import run_replay
    run_replay(config)


if __name__ == "__main__":
    main()
