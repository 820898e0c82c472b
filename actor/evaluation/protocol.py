"""The paper's protocol: each policy from every start of each start set, then one table row per pair."""

from __future__ import annotations

import sys
from typing import Sequence

import numpy as np

from actor.evaluation import EvaluationError
from actor.evaluation.episodes import episode_jobs
from actor.evaluation.status import EvaluationStatus
from actor.evaluation.workers import run_jobs
from actor.sim import START_SETS
from common.analysis.intervals import bootstrap_of
from common.analysis.stats import EvaluationEpisode, SetSummary, summarise_all
from common.config import Config


def evaluate(config: Config, weights: dict[str, np.ndarray] | None, policies: Sequence[str] = ("greedy", "random"),
             start_sets: Sequence[str] = START_SETS, show_status: bool = True
             ) -> tuple[list[EvaluationEpisode], list[SetSummary]]:
    """Runs the protocol for each policy on each start set; returns the episodes and one summary row per pair."""
    edges = config.evaluation.reward_bins
    if edges[0] > 0.0 or edges[-1] < 1.0:
        raise EvaluationError(f"evaluation.reward_bins {edges} must cover [0, 1], the range of step rewards")
    if "greedy" in policies and weights is None:
        raise EvaluationError("the greedy policy needs weights")
    jobs = episode_jobs(policies, start_sets, config.evaluation.episodes_per_start, config.evaluation.seed)
    status = EvaluationStatus(len(jobs), config.evaluation.progress_period_s, sys.stderr if show_status else None,
                              log_period_s=config.evaluation.progress_log_period_s)
    episodes = run_jobs(config, weights, jobs, status)
    return episodes, summarise_all(episodes, bootstrap_of(config))
