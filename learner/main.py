"""`learner`: trains the D3RQN from replayed traces and broadcasts weights and exploration state."""

from __future__ import annotations

import argparse

from common.config import add_config_arguments, parse_config_or_exit, print_config


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="learner",
        description="Learner: trains on the replay's trace batches, which the replay's rate limiter starts "
                    "serving when it holds learner.start_episodes episodes and then paces at one update per "
                    "learner.env_steps_per_update environment steps of the whole system; broadcasts weights "
                    "every learner.weights_every updates and the exploration state (which the actors follow) "
                    "on every change, and checkpoints to <run.runs_dir>/<run.name>/checkpoints.")
    parser.add_argument("--resume", action="store_true",
                        help="continue from the run's latest checkpoint")
    add_config_arguments(parser)
    return parser


def main(argv: list[str] | None = None) -> None:
    args, config = parse_config_or_exit(build_parser(), argv)
    print_config("learner", config)
    from learner.service import run_learner
    run_learner(config, resume=args.resume)


if __name__ == "__main__":
    main()
