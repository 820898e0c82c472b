"""The learner's running figures: its log line and the metrics message it publishes (learner/process.py)."""

from __future__ import annotations

import logging
import math
import time

import numpy as np

from common.wire.metrics import NOT_MEASURED, LearnerStats
from learner.prefetch import Prefetcher
from learner.service import LearnerService
from learner.update import UpdateResult

log = logging.getLogger("learner")


class LearnerMetrics:
    """Running figures for the learner's log line and metrics message."""

    def __init__(self, service: LearnerService, prefetcher: Prefetcher) -> None:
        self.service = service
        self.prefetcher = prefetcher
        self.started = time.monotonic()
        self.losses: list[float] = []
        self.loss_diffs: list[float] = []
        self._previous_loss: float | None = None
        self.grad_norms: list[float] = []  # measured every learner.update.GRAD_NORM_EVERY updates
        self._window_start = (time.monotonic(), service.updates, 0.0)

    def on_update(self, result: UpdateResult) -> None:
        self.loss(result.loss)
        if result.grad_norm is not None:
            self.grad_norms.append(result.grad_norm)

    def loss(self, value: float) -> None:
        if not math.isfinite(value):
            log.warning("non-finite loss %s at update %d", value, self.service.updates)
        if self._previous_loss is not None:
            self.loss_diffs.append(abs(value - self._previous_loss))
        self._previous_loss = value
        self.losses.append(value)

    def report(self, final: bool = False) -> LearnerStats:
        """The figures since the last report, logged and as the metrics message; starts the next report."""
        now = time.monotonic()
        window_time, window_updates, window_data_wait = self._window_start
        elapsed = max(now - window_time, 1e-9)
        updates = self.service.updates
        strategy = self.service.strategy
        achieved = self.service.env_steps_per_update()
        started = math.isfinite(achieved)  # the whole run's ratio, from the replay's start mark
        stats = LearnerStats(
            time=time.time(), updates=updates, env_steps=self.service.clock.env_steps, loss=_mean(self.losses),
            loss_abs_diff=_mean(self.loss_diffs), grad_norm=_mean(self.grad_norms),
            grad_norm_max=float(np.max(self.grad_norms)) if self.grad_norms else NOT_MEASURED,
            epsilon=float(strategy.epsilon), kappa=float(strategy.kappa),
            updates_per_s=(updates - window_updates) / elapsed,
            data_wait_share=(self.prefetcher.wait_s - window_data_wait) / elapsed,
            weights_version=self.service.latest_weights.version if self.service.latest_weights else -1,
            bmc_observations=self.service.bmc_observations, failed_updates=self.service.failed_updates,
            checkpoints_failed=self.service.checkpoint_writes.failed,
            precision=self.service.learner.precision, update_path=self.service.learner.update_path,
            env_steps_per_update=achieved if started else None,
            start_env_steps=float(self.service.clock.start_env_steps) if started else None,
            rejected=self.service.rejections.values(), final=final)
        link = self.service.link
        if link is not None:
            stats.sessions_reopened, stats.hub_silent_s = link.reopened, round(self.service.silent_s(), 1)
            stats.rejected.update({f"malformed_{door}": rejected for door, rejected in link.rejected().items()})
        log.info("updates %d, env steps %d, loss %.5f, epsilon %.3f, %.2f updates/s (%s, update path %s), waiting "
                 "for data %.0f%% of the time, %.3f env steps per update", stats.updates, stats.env_steps, stats.loss,
                 stats.epsilon, stats.updates_per_s, stats.precision, stats.update_path, 100 * stats.data_wait_share,
                 achieved)
        self.losses.clear()
        self.loss_diffs.clear()
        self.grad_norms.clear()
        self._window_start = (now, updates, self.prefetcher.wait_s)
        return stats


def _mean(figures: list[float]) -> float:
    return float(np.mean(figures)) if figures else NOT_MEASURED
