"""The policies the learner keeps for greedy learning curves (learner.keep_every, keep_every_s): the online
weights and, beyond the paper, the shadow kinds beside them (learner.keep_target, learner.ema_updates).

The online weights are copied on the training thread (tens of milliseconds at the paper's
sizes) and written by a thread of their own: an update does not wait for the disk. A keep
that comes while the previous file is still being written waits for it, so at most one
copy of the weights is in flight. With learner.keep_encoding float16 or bfloat16 the
writer rounds the copy first (half the disk); weights the encoding cannot hold are kept
in float32 with a log line, never lost.
"""

from __future__ import annotations

import dataclasses
import logging
import threading

import torch

from common.checkpoint import TRAINED_PRECISIONS, CheckpointError, KeptPolicy
from common.config import Config
from common.config_values import to_dict
from common.run_dir import RunDir
from learner.update import DoubleQLearner

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

    def keep(self, policies: list[KeptPolicy]) -> None:
        """Starts writing the policies of one update (the online one, and the shadow kinds beside it); returns
        once the previous ones are written."""
        self.wait()
        self.last_kept = policies[0].updates
        self._writer = threading.Thread(target=self._write_all, args=(policies,), name="keep-policy", daemon=True)
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

    def _write_all(self, policies: list[KeptPolicy]) -> None:
        for policy in policies:
            self._write(policy)

    def _write(self, policy: KeptPolicy) -> None:
        path = self.run.policy(policy.updates, policy.kind)
        try:
            self._compact(policy).save(path)
        except (OSError, RuntimeError) as error:  # a full disk must not end the training
            self.failed += 1
            log.error("cannot keep the %s policy of update %d in %s: %s", policy.kind, policy.updates, path, error)
            return
        log.info("kept the %s policy of update %d: %s", policy.kind, policy.updates, path)


def policies_now(learner: DoubleQLearner, config: Config, env_steps: int, wall_s: float, cpu: str) -> list[KeptPolicy]:
    """The policies to keep at the learner's current update: the online one, and beside it from
    learner.keep_shadows_from on the target network (learner.keep_target) and the moving average
    (learner.ema_updates): copies, so that training goes on while they are written."""
    precision = learner.precision if learner.precision in TRAINED_PRECISIONS else ""  # not "auto"
    kept = KeptPolicy(updates=learner.updates, env_steps=env_steps, wall_s=wall_s, cpu=cpu, config=to_dict(config),
                      online={}, precision=precision)
    return [dataclasses.replace(kept, online=weights, kind=kind) for kind, weights in kept_weights(learner, config).items()]


def kept_weights(learner: DoubleQLearner, config: Config) -> dict[str, dict[str, torch.Tensor]]:
    """The weights to keep now by kind: online always; target and ema where on, from keep_shadows_from."""
    weights = {"online": {name: torch.from_numpy(array) for name, array in learner.online_weights().items()}}
    if learner.updates < config.learner.keep_shadows_from:
        return weights
    if config.learner.keep_target:
        weights["target"] = {name: tensor.detach().cpu().clone() for name, tensor in learner.target.state_dict().items()}
    if learner.average is not None:
        weights["ema"] = learner.average.state_dict()
    return weights
