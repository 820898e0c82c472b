"""Replay service: subscribes to episodes on <namespace>/<run>/episodes, stores up to
replay.capacity of them (oldest evicted first, within replay.memory_budget_mb), answers
trace-batch queries on <namespace>/<run>/replay/sample and publishes stats. Every episode is
checked against the run's config (frames, actions, rewards) before it is stored, and the store
is snapshotted every replay.snapshot_period_s seconds. Its rate limiter keeps one learner update
per pace.env_steps_per_update env steps: it holds batch replies while the learner is ahead
and tells actors on <namespace>/<run>/replay/rate to hold their next episode while it is behind.
"""

from __future__ import annotations

import argparse

from common.shell import parse_service_args, run_main

RESUME_HELP = ("continue the run's earlier replay: restore its episodes from its snapshot "
               "(<run.runs_dir>/<run.name>/replay/snapshot/) and its rate limiter's counters "
               "(replay/rate_limiter.json); without it the replay starts empty and removes an earlier snapshot")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="replay", description=__doc__)
    parser.add_argument("--resume", action="store_true", help=RESUME_HELP)
    args, config = parse_service_args(parser, argv)
    from replay.process import run_replay
    run_replay(config, resume=args.resume)


if __name__ == "__main__":
    run_main(main)
