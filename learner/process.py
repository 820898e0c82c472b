"""The learner process: its Zenoh session, the training loop that asks the replay for batches and updates
(prefetched), and what it publishes (weights, exploration state, metrics). The service itself, the
learner's state and its doors, is learner/service.py.
"""

from __future__ import annotations

import dataclasses
import logging
import threading

import torch
import zenoh

from common.atomic_file import remove_dead_temporaries
from common.checkpoint import CheckpointError
from common.wire.exploration_state import exploration_message
from common.config import Config
from common.logs import Every
from common.pacing import rate_limit_from_config
from common.hub_link import Declare, HubLink, keep_hearing
from common.run_dir import RunDir
from common.shell import Shell
from common.transport import publisher, request, serve, subscribe
from common.shared_memory import SharedMemory
from common.keys import Keys
from common.wire.messages import TraceBatchRequest, Weights
from common.wire.metrics import LearnerStats
from learner.prefetch import Prefetcher
from learner.metrics import LearnerMetrics
from learner.service import IDLE_POLL_S, SAMPLE_TIMEOUT_S, WAIT_LOG_S, Admitted, Cadence, LearnerService

log = logging.getLogger("learner")


def run_learner(config: Config, resume: bool = False) -> None:
    """Trains until the step budget is spent or SIGINT/SIGTERM; checkpoints at exit."""
    shell = Shell("learner", config)
    shell.claim()  # before the checkpoint is read: a learner that is stopping writes it last
    run = RunDir.of(config)
    remove_dead_temporaries(run.checkpoints, run.policies)
    if config.learner.torch_threads:
        torch.set_num_threads(config.learner.torch_threads)
    service = LearnerService(config)
    if resume:
        try:
            service.resume()
        except CheckpointError as error:
            log.error("cannot resume: %s", error)
            raise SystemExit(1) from None
    log.info("device %s, strategy %s, %d torch threads", service.learner.device,
             config.exploration.strategy, torch.get_num_threads())
    keys = shell.keys
    hearing = threading.Event()  # the session watch stops once training is over
    with shell.session() as session:
        shell.on_close(hearing.set)
        link = HubLink(shell, session, _declaring(service, keys, SharedMemory.of(config.transport)))
        shell.on_close(link.close)
        service.link = link
        threading.Thread(target=keep_hearing, args=(link, service.silent_s, config.learner.silence_reopen_s, hearing),
                         name="hearing", daemon=True).start()
        outputs = Outputs(link, rate_limit_from_config(config).start_by_steps)
        outputs.weights(service.make_weights())
        _train(service, outputs, shell.stop, link, keys)


def _declaring(service: LearnerService, keys: Keys, shared_memory: SharedMemory | None) -> Declare:
    """What the learner declares on a session: its doors (no expected type: a message of another type reaches
    the process, which counts it) and its publishers, weights from shared memory when given some."""
    def declare(session) -> tuple[dict, dict]:
        receivers = {"stats": subscribe(session, keys.replay_stats, service.on_replay_stats),
                     "rate": subscribe(session, keys.replay_rate, service.on_replay_rate),
                     "weights_query": serve(session, keys.weights_latest, service.serve_latest_weights),
                     "weights_pieces": serve(session, keys.weights_pieces, service.serve_weights_piece)}
        publishers = {"weights": publisher(session, keys.weights, shared_memory=shared_memory),
                      "exploration": publisher(session, keys.exploration),
                      "metrics": publisher(session, keys.metrics_source("learner", "0"))}
        return receivers, publishers
    return declare


class Outputs:
    """Everything the learner publishes, on the link's current session."""

    def __init__(self, link: HubLink, start_by_steps: bool | None = None) -> None:
        self._link = link
        self._last_exploration: dict | None = None
        self._start_by_steps = start_by_steps  # the start rule, stated with every exploration state

    def weights(self, weights: Weights) -> None:
        self._link.put("weights", weights)

    def exploration(self, strategy, force: bool = False) -> None:
        state = strategy.state_dict()
        if force or state != self._last_exploration:
            self._link.put("exploration", exploration_message(strategy, self._start_by_steps))
            self._last_exploration = state

    def metrics(self, stats: LearnerStats) -> None:
        self._link.put("metrics", stats)


def _train(service: LearnerService, outputs: Outputs, stop: threading.Event, link: HubLink, keys: Keys) -> None:
    config = service.config.learner
    heartbeat = Every(config.log_period_s)
    broadcasts = Cadence(config.weights_every, config.weights_period_s, min_period_s=config.weights_min_period_s)

    def fetch(message: TraceBatchRequest):
        # Every request states the updates made: the first of this process (its checkpoint's) lets the replay
        # re-owe what a dead learner lost; a later one, what a replay that died with its counters forgot.
        message = dataclasses.replace(message, learner_updates=service.updates)
        try:
            return request(link.session, keys.replay_sample, message, SAMPLE_TIMEOUT_S)
        except zenoh.ZError as error:  # the session closed by a reopen meanwhile: ask again on the fresh one
            log.info("a batch request ended with its session (%s); asking again", error)
            return None

    prefetcher = Prefetcher(fetch, config.batch_size, config.trace_length, config.prefetch, prepare=service.admit)
    if service.strategy.started:  # resumed past the start: actors hold until they have the policy
        outputs.weights(service.make_weights())
        outputs.exploration(service.strategy, force=True)
    batch = _first_batch(service, outputs, prefetcher, stop)
    if batch is None and not service.finished():
        prefetcher.close()
        log.info("stopped before updates started; checkpoint %s", service.try_checkpoint() or "not written")
        return
    if batch is None:
        log.info("resumed with every update the closed run pays for already made (%d): it ends", service.updates)
    else:
        _announce_start(service, outputs, batch)
    metrics = LearnerMetrics(service, prefetcher)

    def idle() -> None:  # while no batch comes: the learner is ahead, or the actors hold
        if heartbeat.due():
            outputs.metrics(metrics.report())
            outputs.exploration(service.strategy, force=True)  # a late actor holds until it has the state
    try:
        while batch is not None:
            result = service.train_on(batch)
            if result is not None:  # None: the batch was refused or its update failed (counted)
                metrics.on_update(result)
                outputs.exploration(service.strategy)
                if broadcasts.due(service.updates):
                    outputs.weights(service.make_weights())
                service.checkpoint_if_due()
                service.keep_policy_if_due()
            if heartbeat.due():
                outputs.metrics(metrics.report())
            batch = _next_batch(service, prefetcher, stop, idle)
    finally:
        prefetcher.close()
        outputs.weights(service.make_weights())
        path = service.try_checkpoint() or "not written (see above)"
        service.keep_last_policy()
        outputs.metrics(metrics.report(final=True))
        log.info("stopped after %d updates, %d env steps, %.3f env steps per update (configured %g); "
                 "checkpoint %s", service.updates, service.clock.env_steps, service.env_steps_per_update(),
                 service.config.pace.env_steps_per_update, path)


def _next_batch(service: LearnerService, prefetcher: Prefetcher, stop: threading.Event, idle) -> Admitted | None:
    """The next batch, or None when stopped or when the closed run is paid for; idle() runs while waiting."""
    while not stop.is_set():
        if service.finished():
            return None
        batch = prefetcher.next(stop, timeout_s=IDLE_POLL_S * 10)
        if batch is not None:
            return batch
        idle()
    return None


def _announce_start(service: LearnerService, outputs: Outputs, batch: Admitted) -> None:
    service.start_updates()
    outputs.exploration(service.strategy, force=True)
    outputs.weights(service.make_weights())  # actors hold from now until they have the learner's policy
    with service._lock:
        mark = service.clock.start_env_steps
    log.info("updates start: the replay's first batch, at %s env steps (start mark %s) with %s episodes stored",
             getattr(batch.batch, "env_steps_total", "?"), "unknown" if mark is None else f"{mark:.0f}",
             getattr(batch.batch, "episodes_stored", "?"))  # perhaps refused: train_on counts that
    _warn_if_bmc_starves(service)


def _first_batch(service: LearnerService, outputs: Outputs, prefetcher: Prefetcher,
                 stop: threading.Event) -> Admitted | None:
    """Waits for the replay's first batch: it comes the moment the replay's rate limiter starts updates.
    None when stopped, or when the run is closed and paid for already (a learner resumed after its last
    update: no batch will come)."""
    config = service.config.learner
    waiting = Every(WAIT_LOG_S)
    while not stop.is_set():
        batch = prefetcher.next(stop, timeout_s=config.log_period_s)
        if batch is not None:
            return batch
        if service.finished():
            return None
        outputs.exploration(service.strategy, force=True)  # late actors learn the state too
        if waiting.due():
            log.info("waiting for the replay to start updates: %d/%d episodes stored, %d env steps",
                     service.episodes_stored, service.config.pace.start_episodes, service.clock.env_steps)
    return None


def _warn_if_bmc_starves(service: LearnerService) -> None:
    config = service.config
    if not service.strategy.needs_returns or config.exploration.bmc.observations != "per_step":
        return
    available = config.learner.batch_size * (config.learner.trace_length - config.learner.masked_steps)
    if config.pace.env_steps_per_update > available:
        log.warning("exploration.bmc.observations per_step: a batch holds %d unmasked transitions, fewer than "
                    "pace.env_steps_per_update %g; BMC observes %d per update", available,
                    config.pace.env_steps_per_update, available)
