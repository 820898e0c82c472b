"""The learner's running figures: its log line and the metrics message it publishes (learner/process.py)."""

from __future__ import annotations

import logging
import math
import time

import numpy as np

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

    def values(self) -> dict:
        now = time.monotonic()
        window_time, window_updates, window_data_wait = self._window_start
        elapsed = max(now - window_time, 1e-9)
        updates = self.service.updates
        strategy = self.service.strategy
        values = {
            "updates": updates,
            "env_steps": self.service.clock.env_steps,
            "loss": float(np.mean(self.losses)) if self.losses else float("nan"),
            # the paper's training figure: |loss_k - loss_k-1| of consecutive updates, averaged here
            "loss_abs_diff": float(np.mean(self.loss_diffs)) if self.loss_diffs else float("nan"),
            # the gradient's global norm before any clip (learner.grad_clip_norm is chosen from these)
            "grad_norm": float(np.mean(self.grad_norms)) if self.grad_norms else float("nan"),
            "grad_norm_max": float(np.max(self.grad_norms)) if self.grad_norms else float("nan"),
            "epsilon": float(strategy.epsilon),
            "kappa": float(strategy.kappa),  # 0: exploring actions are uniform
            "updates_per_s": (updates - window_updates) / elapsed,
            # waiting for a batch: the replay holds replies while the learner is ahead of the ratio
            "data_wait_share": (self.prefetcher.wait_s - window_data_wait) / elapsed,
            "weights_version": self.service.latest_weights.version if self.service.latest_weights else -1,
            "bmc_observations": self.service.bmc_observations,
            "failed_updates": self.service.failed_updates,
            "checkpoints_failed": self.service.checkpoint_writes.failed,  # not written: a full disk, say
            # what the updates actually ran: "auto" resolves on the first batch (learner/update.py)
            "precision": self.service.learner.precision,
            "update_path": self.service.learner.update_path,
            **self.service.rejections.values(),
            **self._link_values(),
        }
        achieved = self.service.env_steps_per_update()
        if math.isfinite(achieved):  # the whole run's ratio, from the replay's start mark
            values["env_steps_per_update"] = achieved
            values["start_env_steps"] = float(self.service.clock.start_env_steps)
        log.info("updates %(updates)d, env steps %(env_steps)d, loss %(loss).5f, epsilon %(epsilon).3f, "
                 "%(updates_per_s).2f updates/s (%(precision)s, update path %(update_path)s), waiting for data "
                 "%(data_wait_share).0f%% of the time, %(ratio).3f env steps per update", {**values, "data_wait_share": 100 * values["data_wait_share"],
                                                      "ratio": achieved})
        self.losses.clear()
        self.loss_diffs.clear()
        self.grad_norms.clear()
        self._window_start = (now, updates, self.prefetcher.wait_s)
        return values

    def _link_values(self) -> dict:
        link = self.service.link
        if link is None:
            return {}
        return {"sessions_reopened": link.reopened, "hub_silent_s": round(self.service.silent_s(), 1),
                **{f"malformed_{door}": rejected for door, rejected in link.rejected().items()}}
