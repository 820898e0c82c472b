"""Learner: trains on the replay's trace batches, which the replay's rate limiter starts serving
when it holds pace.start_episodes episodes and then paces at one update per
pace.env_steps_per_update environment steps of the whole system; broadcasts weights every
learner.weights_every updates (or learner.weights_period_s seconds, whichever comes first), in
learner.weights_encoding, and the exploration state (which the actors follow) on every change,
and checkpoints to <run.runs_dir>/<run.name>/checkpoints.
"""

from __future__ import annotations

import argparse

from common.shell import parse_service_args, run_main


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="learner", description=__doc__)
    parser.add_argument("--resume", action="store_true", help="continue from the run's latest checkpoint")
    args, config = parse_service_args(parser, argv)
    from common.cpu_capability import exit_if_unrunnable  # here, so that --help does not wait for torch
    from common.network import resolve_device
    if resolve_device(config.network).type == "cpu":
        exit_if_unrunnable(parser.prog, {"learner.precision": config.learner.precision})
    from learner.process import run_learner
    run_learner(config, resume=args.resume)


if __name__ == "__main__":
    run_main(main)
