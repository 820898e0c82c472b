"""Where the weights to evaluate come from: a learner checkpoint, or the live learner over Zenoh."""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from actor.evaluation import EvaluationError
from common.checkpoint import Checkpoint, CheckpointError, KeptPolicy
from common.config import Config
from common.config_cli import config_from_args
from common.config_values import from_dict
from common.network import D3RQN, load_numpy_weights
from common.run_dir import RunDir
from common.transport import Keys, open_session, request
from common.wire.errors import WireError
from common.wire.messages import Weights

LIVE_RETRY_S = 0.2


@dataclass
class PolicySource:
    """The weights to evaluate, the config they go with, and where they came from."""

    weights: dict[str, np.ndarray]
    config: Config
    run_dir: RunDir
    facts: dict[str, str]


def checkpoint_source(path: Path, args: argparse.Namespace) -> PolicySource:
    """A checkpoint file, a run folder or its checkpoints folder, or a policy the learner kept."""
    kept = _kept_policy(path)
    if kept is not None:
        config = checkpoint_config(kept.config, args)
        facts = {"source": f"kept policy {kept.path}", "updates": str(kept.updates),
                 "env steps": str(kept.env_steps), "strategy": config.exploration.strategy}
        return PolicySource(kept.weights(), config, RunDir.of_checkpoint(kept.path), facts)
    checkpoint = Checkpoint.load(path)
    weights = checkpoint.policy_weights()
    config = checkpoint_config(checkpoint.config, args)
    facts = {"source": f"checkpoint {checkpoint.path}", "updates": _known(checkpoint.updates),
             "env steps": _known(checkpoint.env_steps), "strategy": config.exploration.strategy}
    return PolicySource(weights, config, RunDir.of_checkpoint(checkpoint.path), facts)


def _kept_policy(path: Path) -> KeptPolicy | None:
    """The kept policy a file holds (policies/policy-u<updates>.pt, or one shipped under results/); None for
    anything else, which Checkpoint.load then reads or refuses."""
    if not path.is_file():
        return None
    try:
        return KeptPolicy.load(path)
    except CheckpointError:
        return None


def _known(count: int | None) -> str:
    return "unknown" if count is None else str(count)


def checkpoint_config(saved: Any, args: argparse.Namespace) -> Config:
    """The checkpoint's config, then --config FILE, then the flags given (--preset does not apply)."""
    if not isinstance(saved, dict):
        raise EvaluationError("the checkpoint's config section is not a table")
    return config_from_args(args, base=from_dict(saved))


def live_source(config: Config) -> PolicySource:
    """The live learner's latest weights, asked for on the run's weights/latest key."""
    keys = Keys(config.transport.namespace, config.run.name)
    with open_session(config.transport) as session:
        reply = _latest_weights(session, keys.weights_latest, config.evaluation.live_timeout_s)
    if reply is None:
        raise EvaluationError(f"no learner answered on {keys.weights_latest} within "
                              f"{config.evaluation.live_timeout_s:g} s")
    try:
        weights = reply.to_float32()  # the learner may send them compact (learner.weights_encoding)
    except WireError as error:
        raise EvaluationError(f"the live learner's weights: {error}") from None
    facts = {"source": f"live learner on {keys.weights_latest}", "weights version": str(reply.version),
             "strategy": config.exploration.strategy}
    return PolicySource(weights, config, RunDir.of(config), facts)


def _latest_weights(session, key: str, timeout_s: float) -> Weights | None:
    """Asks until a learner answers or the time is up: a query returns at once, empty, until
    the learner is up and known to this session."""
    deadline = time.monotonic() + timeout_s
    while True:
        reply = request(session, key, None, max(deadline - time.monotonic(), LIVE_RETRY_S), expected=Weights)
        if isinstance(reply, Weights):
            return reply
        if time.monotonic() >= deadline:
            return None
        time.sleep(LIVE_RETRY_S)


def check_weights(config: Config, weights: dict[str, np.ndarray]) -> None:
    """Fails here, with the reason, rather than in every worker."""
    try:
        load_numpy_weights(D3RQN(config.network), weights)
    except ValueError as error:
        raise EvaluationError(f"the weights do not fit the configured network: {error}") from None
