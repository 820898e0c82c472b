"""Where the weights to evaluate come from: a learner checkpoint, or the live learner over Zenoh."""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from actor.evaluation import EvaluationError
from common.checkpoint import KeptPolicy, load_checkpoint_or_policy
from common.config import Config
from common.config_cli import config_from_args
from common.config_values import from_dict
from common.network import D3RQN, load_numpy_weights
from common.run_dir import RunDir
from common.transport import open_session, request
from common.keys import Keys
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
    """A checkpoint file, a run folder or its checkpoints folder, or a policy the learner kept
    (policies/policy-u<updates>.pt) or that was shipped in 16 bits (deploy/tools/ship_policy.py)."""
    saved = load_checkpoint_or_policy(path)
    if isinstance(saved, KeptPolicy):
        config = checkpoint_config(saved.config, args)
        shipped = "" if saved.encoding == "float32" else f" ({saved.encoding} weights, widened to float32)"
        facts = {"source": f"kept policy {saved.path}{shipped}", "updates": str(saved.updates),
                 "env steps": str(saved.env_steps), "strategy": config.exploration.strategy}
        if saved.averaged:
            facts["averaged"] = f"the mean of {len(saved.averaged)} kept policies' weights, updates " \
                                f"{', '.join(str(updates) for updates in saved.averaged)}"
        return PolicySource(saved.weights(), config, RunDir.of_checkpoint(saved.path), facts)
    weights = saved.policy_weights()
    config = checkpoint_config(saved.config, args)
    facts = {"source": f"checkpoint {saved.path}", "updates": _known(saved.updates),
             "env steps": _known(saved.env_steps), "strategy": config.exploration.strategy}
    return PolicySource(weights, config, RunDir.of_checkpoint(saved.path), facts)


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
