"""`actor`: one actor process. Drives the simulator with the latest weights and publishes episodes."""

from __future__ import annotations

import argparse

from common.config import add_config_arguments, parse_config_or_exit, print_config


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="actor",
        description="Actor: steps the driving simulator with the learner's latest weights and exploration "
                    "state, and publishes every finished episode to the replay (finished episodes wait in a bounded "
                    "outbox, actor.queue_episodes and actor.queue_mb, while no replay listens). Weights, exploration "
                    "state and rate messages are checked before they are used. Give each actor its own "
                    "--actor.actor_id; its seed derives from --run.seed and the id.")
    parser.add_argument("--max-episodes", type=int, default=None,
                        help="stop after this many episodes (default: run until stopped)")
    add_config_arguments(parser)
    return parser


def main(argv: list[str] | None = None) -> None:
    args, config = parse_config_or_exit(build_parser(), argv)
    print_config("actor", config)
    from actor.runner import run_actor
    run_actor(config, max_episodes=args.max_episodes)


if __name__ == "__main__":
    main()
