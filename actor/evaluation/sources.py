"""Where the weights to evaluate come from: a learner checkpoint, or the live learner over Zenoh."""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from actor.evaluation import EvaluationError
from common.config import Config, config_from_args, from_dict
from common.network import D3RQN, load_numpy_weights
from common.transport import Keys, open_session, request
from common.wire import Weights
from learner.checkpoint import LATEST, load_checkpoint

CHECKPOINTS_DIR = "checkpoints"  # learner/service.py writes <runs_dir>/<run>/checkpoints/latest.pt
LIVE_RETRY_S = 0.2


@dataclass
class PolicySource:
    """The weights to evaluate, the config they go with, and where they came from."""

    weights: dict[str, np.ndarray]
    config: Config
    run_dir: Path
    facts: dict[str, str]


def locate_checkpoint(path: Path) -> tuple[Path, Path]:
    """(checkpoint file, run directory) for a checkpoint file, a checkpoints directory or a run directory."""
    if path.is_file():
        return path, path.parent.parent if path.parent.name == CHECKPOINTS_DIR else path.parent
    if (path / CHECKPOINTS_DIR / LATEST).is_file():
        return path / CHECKPOINTS_DIR / LATEST, path
    if (path / LATEST).is_file():
        return path / LATEST, path.parent if path.name == CHECKPOINTS_DIR else path
    raise EvaluationError(f"no checkpoint at {path}: expected a checkpoint file, a run directory with "
                          f"{CHECKPOINTS_DIR}/{LATEST}, or a directory with {LATEST}")


def checkpoint_source(path: Path, args: argparse.Namespace) -> PolicySource:
    file, run_dir = locate_checkpoint(path)
    payload = load_checkpoint(file, ("learner", "config"))
    learner = payload["learner"]
    if not isinstance(learner, dict) or "online" not in learner:
        raise EvaluationError(f"checkpoint {file} has no online network in its learner section")
    config = checkpoint_config(payload["config"], args)
    weights = {name: tensor.detach().cpu().numpy() for name, tensor in learner["online"].items()}
    env_steps = payload.get("clock", {}).get("env_steps", "unknown")
    facts = {"source": f"checkpoint {file}", "updates": str(learner.get("updates", "unknown")),
             "env steps": str(env_steps), "strategy": config.exploration.strategy}
    return PolicySource(weights, config, run_dir, facts)


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
    facts = {"source": f"live learner on {keys.weights_latest}", "weights version": str(reply.version),
             "strategy": config.exploration.strategy}
    return PolicySource(dict(reply.tensors), config, Path(config.run.runs_dir) / config.run.name, facts)


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
