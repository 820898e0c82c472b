"""Where an evaluation's failed episodes ended: what each collision touched, where each car left the road or
stalled, pooled by place (common/analysis/tables.failures_by_site, the table evaluate writes into summary.md).

Evaluations since the end pose was kept carry it in episodes.csv. For an older one, the failed episodes are
replayed with the policy that was evaluated: the same simulator, seeds and greedy float32 actions, so a replay
is the recorded episode again; each replay's action digest is checked against the recorded one, and a
mismatch (another policy, another config) is an error, not a table.

    .venv/bin/python deploy/tools/failure_sites.py runs/grid/mbe-b1000-s1/evaluation
    .venv/bin/python deploy/tools/failure_sites.py results/grid/runs/mbe-b1000-s1/evaluation \\
        --policy runs/grid/mbe-b1000-s1/policies/policy-u0028000.pt --start-set test --write

--write puts the replayed places into the evaluation's episodes.csv (a new file moved over the old one, so that
a failure leaves the old one whole), where the grid report and later calls read them.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import os
import sys
from pathlib import Path

import torch

from actor.evaluation import EvaluationError
from actor.evaluation.episodes import EpisodeJob
from actor.evaluation.sources import checkpoint_source
from actor.evaluation.status import EvaluationStatus
from actor.evaluation.workers import run_jobs
from common.analysis.stats import SITE_FIELDS, EvaluationEpisode
from common.analysis.tables import EPISODES_CSV, failure_site, failures_by_site
from common.checkpoint import CheckpointError
from common.config_cli import add_config_arguments, parse_flags
from common.schema.fields import ConfigError
from deploy.studies.comparison import ComparisonError, read_episodes_csv

GREEDY = "greedy"


def failed_episodes(episodes: list[EvaluationEpisode], start_set: str | None) -> list[EvaluationEpisode]:
    return [episode for episode in episodes if episode.policy == GREEDY and not episode.collision_free
            and start_set in (None, episode.start_set)]


def replayed(args: argparse.Namespace, failed: list[EvaluationEpisode]) -> list[EvaluationEpisode]:
    """The failed episodes driven again by --policy, each checked against its recorded actions."""
    if args.policy is None:
        raise EvaluationError("this evaluation's episodes.csv has no end poses (it is older): give --policy, "
                              "the policy it evaluated, to replay its failed episodes")
    source = checkpoint_source(args.policy, args)
    jobs = [EpisodeJob(GREEDY, episode.start_set, episode.start_index, episode.trial, episode.seed)
            for episode in failed]
    status = EvaluationStatus(len(jobs), 10.0)
    again = run_jobs(source.config, source.weights, jobs, status)
    for recorded, replay in zip(failed, again):
        if (replay.actions_digest, replay.length) != (recorded.actions_digest, recorded.length):
            raise EvaluationError(
                f"{recorded.start_set} start {recorded.start_index} trial {recorded.trial}: the replay took other "
                f"actions ({replay.length} steps, digest {replay.actions_digest}) than the recorded episode "
                f"({recorded.length} steps, {recorded.actions_digest}); is --policy the policy evaluated, with "
                "its config?")
    return [dataclasses.replace(recorded, **{name: getattr(replay, name) for name in SITE_FIELDS})
            for recorded, replay in zip(failed, again)]


def write_sites(path: Path, replays: list[EvaluationEpisode]) -> None:
    """episodes.csv again with the place columns, filled for the replayed episodes; every other cell is kept as
    it was written."""
    with path.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    again = {(e.policy, e.start_set, e.start_index, e.trial): e for e in replays}
    for row in rows:
        replay = again.get((row["policy"], row["start_set"], int(row["start_index"]), int(row["trial"])))
        if replay is not None:  # a row replayed before (another --start-set) keeps its places
            row.update({name: getattr(replay, name) for name in SITE_FIELDS})
    fresh = path.with_name(path.name + ".new")
    with fresh.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(dict.fromkeys([*rows[0], *SITE_FIELDS])), restval="")
        writer.writeheader()
        writer.writerows(rows)
    os.replace(fresh, path)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="deploy/tools/failure_sites.py", description=__doc__.splitlines()[0])
    parser.add_argument("evaluation", type=Path, help="an evaluation folder (evaluate's output, with episodes.csv)")
    parser.add_argument("--policy", type=Path, help="the policy it evaluated (a kept policy, a checkpoint or a run "
                                                    "folder): needed only for an evaluation without end poses")
    parser.add_argument("--start-set", choices=("train", "test"), help="only this start set's failures")
    parser.add_argument("--write", action="store_true", help="put the replayed places into the evaluation's "
                                                             "episodes.csv")
    add_config_arguments(parser)  # the policy's config, changed only by --config FILE and the flags given
    args = parse_flags(parser, argv)
    torch.set_num_threads(1)
    try:
        episodes, _ = read_episodes_csv(args.evaluation / EPISODES_CSV)
        failed = failed_episodes(episodes, args.start_set)
        if failed and not all(failure_site(episode) for episode in failed):
            failed = replayed(args, failed)
            if args.write:
                write_sites(args.evaluation / EPISODES_CSV, failed)
    except (ComparisonError, CheckpointError, ConfigError, EvaluationError, OSError) as error:
        print(f"failure_sites: error: {error}", file=sys.stderr)
        return 1
    lines = failures_by_site(failed)
    print("\n".join(lines) if lines else "Every greedy episode reached the cap.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
