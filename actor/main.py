"""Actor: steps the driving simulator with the learner's latest weights and exploration state,
and publishes every finished episode to the replay (finished episodes wait in a bounded outbox,
actor.queue_episodes and actor.queue_mb, while no replay listens). Weights, exploration state
and rate messages are checked before they are used. Give each actor its own --actor.actor_id;
its seed derives from --run.seed and the id.
"""

from __future__ import annotations

import argparse

from common.shell import parse_service_args, run_main


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="actor", description=__doc__)
    parser.add_argument("--max-episodes", type=int, default=None,
                        help="stop after this many episodes (default: run until stopped)")
    args, config = parse_service_args(parser, argv)
    from common.cpu_capability import exit_if_unrunnable  # here, so that --help does not wait for torch
    exit_if_unrunnable(parser.prog, {"actor.inference": config.actor.inference})
    from actor.runner import run_actor
    run_actor(config, max_episodes=args.max_episodes)


if __name__ == "__main__":
    run_main(main)
