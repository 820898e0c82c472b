"""Runs evaluation jobs on spawned worker processes and collects their episodes in job order."""

from __future__ import annotations

import math
import multiprocessing
import os
import queue
from typing import Sequence

import numpy as np

from actor.evaluation import EvaluationError
from actor.evaluation.episodes import EpisodeJob, WorkerDone, WorkerFailed, evaluation_worker
from actor.evaluation.status import EvaluationStatus
from common.analysis.stats import EvaluationEpisode
from common.config import Config
from common.sim_config import EvaluationConfig

WORKER_EXIT_TIMEOUT_S = 10.0


def torch_threads_per_worker(evaluation: EvaluationConfig, workers: int) -> int:
    return evaluation.torch_threads or max(1, len(os.sched_getaffinity(0)) // workers)


def worker_layout(evaluation: EvaluationConfig, jobs: int) -> tuple[int, int, int]:
    """(processes, lockstep simulators each, torch threads each) for this many jobs: no more processes than
    jobs, and no more simulators than a process's share of them. Every worker fills all its simulators from
    the shared queue at once, so without the cap the first to start would take more than its share of a short
    queue (a curve's 50 or 100 episodes) while the others idle, and simulators that never get a job would be
    built for nothing."""
    workers = max(1, min(evaluation.workers, jobs))
    simulators = max(1, min(evaluation.envs_per_worker, math.ceil(jobs / workers)))
    return workers, simulators, torch_threads_per_worker(evaluation, workers)


def run_jobs(config: Config, weights: dict[str, np.ndarray] | None, jobs: Sequence[EpisodeJob],
             status: EvaluationStatus) -> list[EvaluationEpisode]:
    """Runs the jobs on spawned processes (worker_layout); the episodes come back in job order."""
    context = multiprocessing.get_context("spawn")
    job_queue, result_queue = context.Queue(), context.Queue()
    n_workers, simulators, threads = worker_layout(config.evaluation, len(jobs))
    workers = [context.Process(target=evaluation_worker, name=f"evaluate-{number}", daemon=True,
                               args=(number, config, weights, simulators, threads, job_queue, result_queue))
               for number in range(n_workers)]
    try:
        for job in [*jobs, *[None] * n_workers]:  # one end marker per worker
            job_queue.put(job)
        for worker in workers:
            worker.start()
        episodes = _collect(result_queue, workers, status)
    except BaseException:  # interrupted, or a worker failed: the others' episodes are not wanted
        for worker in _started(workers):
            worker.terminate()
        raise
    finally:
        _join(_started(workers))
        # jobs no worker took (an interruption) would hold this process at exit, its feeder thread waiting to
        # write them into a pipe nobody reads
        job_queue.cancel_join_thread()
    order = {(job.policy, job.start_set, job.start_index, job.trial): rank for rank, job in enumerate(jobs)}
    episodes.sort(key=lambda e: order[(e.policy, e.start_set, e.start_index, e.trial)])
    if len(episodes) != len(jobs):
        raise EvaluationError(f"expected {len(jobs)} episodes, the workers returned {len(episodes)}")
    return episodes


def _started(workers: list) -> list:
    return [worker for worker in workers if worker.pid is not None]


def _join(workers: list) -> None:
    for worker in workers:
        worker.join(WORKER_EXIT_TIMEOUT_S)
        if worker.is_alive():
            worker.terminate()
            worker.join()


def _collect(result_queue, workers: list, status: EvaluationStatus) -> list[EvaluationEpisode]:
    episodes: list[EvaluationEpisode] = []
    finished: set[int] = set()
    while len(finished) < len(workers):
        try:
            item = result_queue.get(timeout=status.period_s)
        except queue.Empty:
            crashed = [worker.name for worker in workers if worker.exitcode not in (None, 0)]
            if crashed:
                raise EvaluationError(f"worker(s) {', '.join(crashed)} died without a report") from None
            status.tick()
            continue
        if isinstance(item, EvaluationEpisode):
            episodes.append(item)
            status.add(item)
        elif isinstance(item, WorkerDone):
            finished.add(item.worker_id)
        elif isinstance(item, WorkerFailed):
            raise EvaluationError(f"worker {item.worker_id} failed:\n{item.error}")
    status.show(final=True)
    return episodes
