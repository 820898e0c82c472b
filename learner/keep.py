"""The policies the learner keeps for greedy learning curves (learner.keep_every, keep_every_s).

The online weights are copied on the training thread (tens of milliseconds at the paper's
sizes) and written by a thread of their own: an update does not wait for the disk. A keep
that comes while the previous file is still being written waits for it, so at most one
copy of the weights is in flight. With learner.keep_encoding float16 or bfloat16 the
writer rounds the copy first (half the disk); weights the encoding cannot hold are kept
in float32 with a log line, never lost.
"""

from __future__ import annotations

import logging
import threading

from common.checkpoint import CheckpointError, KeptPolicy
from common.run_dir import RunDir

log = logging.getLogger("learner")


class PolicyKeeper:
    """Writes kept policies to <run>/policies/ when `cadence` says so."""

    def __init__(self, run: RunDir, cadence, encoding: str = "float32") -> None:
        self.run = run
        self.cadence = cadence  # learner.service.Cadence, or None: keeping is off
        self.encoding = encoding  # learner.keep_encoding
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

    def _compact(self, policy: KeptPolicy) -> KeptPolicy:
        if self.encoding == "float32":
            return policy
        try:
            return policy.compact(self.encoding)
        except CheckpointError as error:  # a weight beyond float16's range, or a NaN: keep it as trained
            log.warning("the policy of update %d is kept in float32, not %s: %s", policy.updates, self.encoding, error)
            return policy

    def _write(self, policy: KeptPolicy) -> None:
        path = self.run.policy(policy.updates)
        try:
            self._compact(policy).save(path)
        except (OSError, RuntimeError) as error:  # a full disk must not end the training
            self.failed += 1
            log.error("cannot keep the policy of update %d in %s: %s", policy.updates, path, error)
            return
        log.info("kept the policy of update %d: %s", policy.updates, path)
