"""The policies the learner keeps for greedy learning curves (learner.keep_every, keep_every_s).

The online weights are copied on the training thread (tens of milliseconds at the paper's
sizes) and written by a thread of their own: an update does not wait for the disk. A keep
that comes while the previous file is still being written waits for it, so at most one
copy of the weights is in flight.
"""

from __future__ import annotations

import logging
import threading

from common.checkpoint import KeptPolicy
from common.run_dir import RunDir

log = logging.getLogger("learner")


class PolicyKeeper:
    """Writes kept policies to <run>/policies/ when `cadence` says so."""

    def __init__(self, run: RunDir, cadence) -> None:
        self.run = run
        self.cadence = cadence  # learner.service.Cadence, or None: keeping is off
        self.last_kept: int | None = None  # the updates of the latest policy kept
        self.failed = 0
        self._writer: threading.Thread | None = None

    def due(self, updates: int) -> bool:
        return self.cadence is not None and self.cadence.due(updates)

    def keep(self, policy: KeptPolicy) -> None:
        """Starts writing the policy; returns once the previous one is written."""
        self.wait()
        self.last_kept = policy.updates
        self._writer = threading.Thread(target=self._write, args=(policy,), name="keep-policy", daemon=True)
        self._writer.start()

    def wait(self) -> None:
        if self._writer is not None:
            self._writer.join()
            self._writer = None

    def _write(self, policy: KeptPolicy) -> None:
        path = self.run.policy(policy.updates)
        try:
            policy.save(path)
        except (OSError, RuntimeError) as error:  # a full disk must not end the training
            self.failed += 1
            log.error("cannot keep the policy of update %d in %s: %s", policy.updates, path, error)
            return
        log.info("kept the policy of update %d: %s", policy.updates, path)
