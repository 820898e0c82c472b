"""Evaluation episodes: which to run, the policies that drive them, and lockstep stepping.

One worker process holds ``envs_per_worker`` simulators (fewer for a short
queue: workers.worker_layout) and steps them in lockstep, on the acting core
that steps the training episodes (actor/lockstep.py): at every step the
greedy network sees all its running episodes in one batched forward pass,
each with its own LSTM state, which is zeroed when that slot starts a new
episode. A slot whose episode ends takes the next job
at once, so slow and fast episodes mix freely. Episodes of the random and
privileged baselines run in the same loop without the network, and so does
the privileged driver that turns right wherever it can ("right-turns"), which
goes round one loop of the grid: it reaches the cap over few streets, the
reference for the coverage columns (streets and junctions visited).

The simulator is deterministic: a start pose and an action sequence fix the
whole episode. Each trial still resets its env with its own seed, and the
random baseline and the privileged driver (random turns at junctions) draw
from it, so their trials differ; the greedy policy has nothing random left,
so its trials from one start repeat each other. The statistics report how many
distinct trajectories each start produced rather than assume either way.
"""

from __future__ import annotations

import dataclasses
import math
import os
import queue
import traceback
from dataclasses import dataclass
from typing import Callable, Iterable, Iterator, Protocol

import numpy as np
import torch

from actor.batched_q import BatchedQ
from actor.lockstep import Lockstep, Trajectory
from actor.sim import START_SETS, make_env, start_poses
from actor.sim.neighbourhood import place_counts
from actor.sim.privileged import PrivilegedDriver
from common.analysis.stats import TERMINAL_REASONS, EvaluationEpisode, digest_of_actions, reward_bin_counts
from common.config import Config
from common.sim_config import EnvConfig
from common.network import D3RQN, load_numpy_weights

POLICIES = ("greedy", "random", "privileged", "right-turns")
JOB_POLL_S = 1.0  # how often a worker waiting on an empty job queue looks whether its parent still lives

Pose = tuple[float, float, float]


@dataclass(frozen=True)
class EpisodeJob:
    policy: str
    start_set: str
    start_index: int
    trial: int
    seed: int


def trial_seed(root_seed: int, start_set: str, start_index: int, trial: int) -> int:
    """Reproducible, independent seeds; the same for every policy, so baselines face the same draws."""
    entropy = [root_seed, START_SETS.index(start_set), start_index, trial]
    return int(np.random.SeedSequence(entropy).generate_state(1)[0])


def episode_jobs(policies: Iterable[str], start_sets: Iterable[str], trials: int, root_seed: int) -> list[EpisodeJob]:
    """Every (policy, set, start, trial), greedy first so the batched network runs on full batches."""
    return [EpisodeJob(policy, start_set, index, trial, trial_seed(root_seed, start_set, index, trial))
            for policy in policies
            for start_set in start_sets
            for index in range(len(start_poses(start_set)))
            for trial in range(trials)]


def evaluation_env_config(config: Config) -> EnvConfig:
    """The training env with the evaluation's step cap."""
    return dataclasses.replace(config.env, max_steps=config.evaluation.max_steps)


# --- policies: each acts for a batch of slots -------------------------------------------------

class Policy(Protocol):
    def begin(self, slot: int, job: EpisodeJob, pose: Pose) -> None:
        """Forgets the slot's previous episode and prepares for this one."""

    def act(self, slots: list[int], observations: list[np.ndarray], poses: list[Pose]) -> list[int]:
        """One action per slot."""


class GreedyPolicy(BatchedQ):
    """argmax Q, one batched forward pass per step, one LSTM state per slot."""

    def begin(self, slot: int, job: EpisodeJob, pose: Pose) -> None:
        self.reset(slot)

    def act(self, slots: list[int], observations: list[np.ndarray], poses: list[Pose]) -> list[int]:
        return self.q_values(slots, observations).argmax(dim=-1).tolist()


class RandomPolicy:
    """Uniform actions from the trial's seed."""

    def __init__(self, n_actions: int, n_slots: int) -> None:
        self.n_actions = n_actions
        self.rngs: list[np.random.Generator | None] = [None] * n_slots

    def begin(self, slot: int, job: EpisodeJob, pose: Pose) -> None:
        self.rngs[slot] = np.random.default_rng(job.seed)

    def act(self, slots: list[int], observations: list[np.ndarray], poses: list[Pose]) -> list[int]:
        return [int(self.rngs[slot].integers(self.n_actions)) for slot in slots]


class PrivilegedPolicy:
    """The map-reading driver of actor.sim.privileged: an upper bound, not a learner; with turns "right"
    (or "left") a route that goes round one loop of the grid."""

    def __init__(self, env_config: EnvConfig, n_slots: int, turns: str = "random") -> None:
        self.env_config = env_config
        self.turns = turns
        self.drivers: list[PrivilegedDriver | None] = [None] * n_slots

    def begin(self, slot: int, job: EpisodeJob, pose: Pose) -> None:
        driver = PrivilegedDriver(self.env_config, seed=job.seed, turns=self.turns)
        driver.reset(pose)
        self.drivers[slot] = driver

    def act(self, slots: list[int], observations: list[np.ndarray], poses: list[Pose]) -> list[int]:
        return [self.drivers[slot].act(pose) for slot, pose in zip(slots, poses)]


def make_policies(config: Config, weights: dict[str, np.ndarray] | None, n_slots: int) -> dict[str, Policy]:
    """Every policy a worker may be asked to run; greedy only when there are weights."""
    policies: dict[str, Policy] = {
        "random": RandomPolicy(config.network.n_actions, n_slots),
        "privileged": PrivilegedPolicy(evaluation_env_config(config), n_slots),
        "right-turns": PrivilegedPolicy(evaluation_env_config(config), n_slots, turns="right"),
    }
    if weights is not None:
        network = D3RQN(config.network)
        load_numpy_weights(network, weights)
        policies["greedy"] = GreedyPolicy(network, n_slots)
    return policies


# --- lockstep stepping -------------------------------------------------------------------------

def evaluation_episode(job: EpisodeJob, trajectory: Trajectory, max_steps: int,
                       reward_edges: list[float]) -> EvaluationEpisode:
    """The record of an ended evaluation episode."""
    info = trajectory.info
    # the simulator cut it at its own cap: evaluation_env_config makes that max_steps
    end = end_reason(info, trajectory.terminated, trajectory.length, max_steps) or "cap"
    streets, junctions = coverage_of(info.get("streets_visited"))
    end_x, end_y, end_heading = pose_of(info)
    return EvaluationEpisode(
        policy=job.policy, start_set=job.start_set, start_index=job.start_index, trial=job.trial,
        seed=job.seed, length=trajectory.length, end=end, episode_return=float(sum(trajectory.rewards)),
        reward_bin_counts=reward_bin_counts(trajectory.rewards, reward_edges),
        actions_digest=digest_of_actions(trajectory.actions), progress_m=progress_of(info),
        streets=streets, junctions=junctions, end_x=end_x, end_y=end_y, end_heading=end_heading,
        end_place=str(info.get("street") or ""), hit=str(info.get("hit") or ""))


def end_reason(info: dict, terminated: bool, length: int, max_steps: int) -> str | None:
    """Why the episode ended after this step, or None if it goes on.

    A terminated episode ends for the reason the simulator gives in info["end"]
    (one of TERMINAL_REASONS); a simulator without it is read from its collision
    and offroad flags, a collision winning. An episode that goes on to the step
    cap ends by "cap", whatever info["end"] says of the cut.
    """
    if terminated:
        reason = info.get("end")
        if reason is None:
            reason = "collision" if info.get("collision") else "offroad" if info.get("offroad") else None
        if reason not in TERMINAL_REASONS:
            raise ValueError(f"the env ended an episode for a reason the evaluation does not know: {info}")
        return reason
    return "cap" if length >= max_steps else None


def progress_of(info: dict) -> float:
    """Metres of progress along the road this episode, NaN when the simulator does not report it."""
    value = info.get("progress_m")
    return math.nan if value is None else float(value)


def pose_of(info: dict) -> tuple[float, float, float]:
    """The car's (x, y, heading) at the episode's last step, NaNs when the simulator does not report it."""
    pose = info.get("pose")
    return (math.nan,) * 3 if pose is None else tuple(float(value) for value in pose)


def coverage_of(places: tuple[str, ...] | None) -> tuple[float, float]:
    """(distinct streets, distinct junctions) an episode visited, from the simulator's
    info["streets_visited"]; NaN for both when the simulator does not report it."""
    if places is None:
        return math.nan, math.nan
    return place_counts(places)


def run_lockstep(jobs: Iterable[EpisodeJob], envs: list, policies: dict[str, Policy], max_steps: int,
                 reward_edges: list[float], on_episode: Callable[[EvaluationEpisode], None],
                 wanted: Callable[[], bool] = lambda: True) -> None:
    """Runs every job on the envs, len(envs) at a time, on the acting core (actor/lockstep.py) that steps
    the training episodes; calls on_episode as each one ends. Stops between two steps once wanted() is false
    (a worker whose parent is gone), leaving the episodes under way unfinished."""
    pending: Iterator[EpisodeJob] = iter(jobs)
    core = Lockstep(envs, max_steps, keep_frames=False)
    jobs_of: dict[int, EpisodeJob] = {}

    def start_next(slot: int) -> None:
        job = next(pending, None)
        if job is None:
            return
        if job.policy not in policies:
            raise ValueError(f"no {job.policy!r} policy in this worker (have {sorted(policies)})")
        core.begin(slot, seed=job.seed, options={"start_set": job.start_set, "start_index": job.start_index})
        policies[job.policy].begin(slot, job, envs[slot].unwrapped.pose)
        jobs_of[slot] = job

    for slot in range(len(envs)):
        start_next(slot)
    while core.running and wanted():
        for slot, trajectory in core.step(choose_actions(core, jobs_of, policies)):
            on_episode(evaluation_episode(jobs_of.pop(slot), trajectory, max_steps, reward_edges))
            start_next(slot)


def choose_actions(core: Lockstep, jobs_of: dict[int, EpisodeJob], policies: dict[str, Policy]) -> dict[int, int]:
    """One call per policy over all the running slots it drives."""
    actions: dict[int, int] = {}
    for name, policy in policies.items():
        slots = [slot for slot in core.running if jobs_of[slot].policy == name]
        if slots:
            chosen = policy.act(slots, [core.running[slot].observation for slot in slots],
                                [core.envs[slot].unwrapped.pose for slot in slots])
            actions.update(zip(slots, chosen))
    return actions


# --- the worker process --------------------------------------------------------------------------

@dataclass(frozen=True)
class WorkerDone:
    worker_id: int


@dataclass(frozen=True)
class WorkerFailed:
    worker_id: int
    error: str


def queued_jobs(job_queue, parent_pid: int | None = None) -> Iterator[EpisodeJob]:
    """Jobs from a shared queue until this worker's end marker (None), or until the process that started
    it (parent_pid) is gone: killed, it can read no episode, and its queue holds jobs for hours. A killed
    parent also leaves the queue without its end markers (they were still in its feeder thread), so an empty
    queue is waited on in short polls that look at the parent between them, never in one blocking get."""
    while parent_pid is None or os.getppid() == parent_pid:
        try:
            job = job_queue.get(timeout=JOB_POLL_S)
        except queue.Empty:
            continue
        if job is None:
            return
        yield job


def evaluation_worker(worker_id: int, config: Config, weights: dict[str, np.ndarray] | None, n_slots: int,
                      torch_threads: int, job_queue, result_queue, parent_pid: int | None = None) -> None:
    """Process entry point: runs queued jobs on n_slots simulators in lockstep, puts each EvaluationEpisode on
    result_queue, then WorkerDone, or WorkerFailed with the traceback. If the parent dies, the worker stops at
    its next step (64 simulators' episodes at the cap would take minutes to finish for nobody) and exits without
    waiting to hand over what nobody reads."""
    parent_pid = os.getppid() if parent_pid is None else parent_pid
    envs = []
    try:
        torch.set_num_threads(torch_threads)
        envs = [make_env(evaluation_env_config(config)) for _ in range(n_slots)]
        run_lockstep(queued_jobs(job_queue, parent_pid), envs, make_policies(config, weights, n_slots),
                     config.evaluation.max_steps, config.evaluation.reward_bins, result_queue.put,
                     wanted=lambda: os.getppid() == parent_pid)
        if os.getppid() != parent_pid:
            result_queue.cancel_join_thread()  # its reader is gone: exiting must not wait on a full pipe
            return
        result_queue.put(WorkerDone(worker_id))
    except BaseException:  # the parent must hear of any failure, or it would wait forever
        result_queue.put(WorkerFailed(worker_id, traceback.format_exc()))
    finally:
        for env in envs:
            env.close()
