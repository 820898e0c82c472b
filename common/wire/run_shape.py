"""Does a decoded message fit the run? Frames of another size, actions outside the action space and
absurd rewards decode, and are refused here.

``RunShape`` holds what a run's messages must fit, ``check_episode`` and ``check_trace_batch`` check it
(every frame of an episode is decompressed), and ``stat_number`` reads one value of a flat counters row
(common/wire/messages.py flat_values; an untyped Stats' values) without trusting it. Each refusal is a WireError with a ``kind`` (a short name for counting:
common/rejections.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from common.wire.state_rows import stored_units
from common.wire.errors import WireError
from common.wire.frames import FrameStack
from common.wire.messages import Episode, TraceBatch


@dataclass(frozen=True)
class RunShape:
    """What the messages of one run must fit, from its configuration."""

    frame_shape: tuple[int, int, int]  # H, W, C of every observation
    n_actions: int  # actions are indices in [0, n_actions)
    max_steps: int  # no episode is longer (env.max_steps)
    reward_limit: float  # |reward| above this is absurd (the env's rewards lie in [0, 1])
    state_units: int = 0  # learner.stored_state: episodes carry LSTM state rows of this many units; 0: none used

    @classmethod
    def of(cls, config: Any) -> RunShape:
        """The shape of a run's Config (common/config.py)."""
        network = config.network
        return cls((network.frame_height, network.frame_width, network.frame_channels), network.n_actions,
                   config.env.max_steps, config.replay.reward_limit, stored_units(config))


def _misfit(kind: str, text: str) -> WireError:
    return WireError(text, kind)


def _check_steps(actions: np.ndarray, rewards: np.ndarray, frames: FrameStack, shape: RunShape, what: str) -> None:
    if frames.frame_shape != shape.frame_shape:
        raise _misfit("frame_shape", f"{what}: frames of shape {list(frames.frame_shape)}, the run's are "
                                     f"{list(shape.frame_shape)}")
    if actions.size and (actions.min() < 0 or actions.max() >= shape.n_actions):
        raise _misfit("actions", f"{what}: actions in [{actions.min()}, {actions.max()}], the run has "
                                 f"{shape.n_actions} actions")
    if rewards.size and float(np.abs(rewards).max()) > shape.reward_limit:
        raise _misfit("rewards", f"{what}: a reward of magnitude {float(np.abs(rewards).max()):.3g} exceeds "
                                 f"replay.reward_limit {shape.reward_limit:g}")


def check_episode(episode: Episode, shape: RunShape) -> None:
    """Raises WireError (with its kind) unless the decoded episode fits the run; decompresses every frame."""
    if len(episode) > shape.max_steps:
        raise _misfit("length", f"Episode: {len(episode)} steps, more than env.max_steps {shape.max_steps}")
    _check_steps(np.asarray(episode.actions), np.asarray(episode.rewards), episode.observations, shape, "Episode")
    _check_state_rows(episode.recurrent_state, len(episode), shape, "Episode.recurrent_state")
    if np.min(episode.weights_version) < -1:  # -1: acted before any weights
        raise _misfit("weights_version", "Episode: a weights version below -1")
    try:
        episode.observations.verify()
    except WireError as error:
        raise _misfit("frames_corrupt", f"Episode.observations: {error}") from None


def check_trace_batch(batch: TraceBatch, shape: RunShape, batch_size: int, trace_length: int) -> None:
    """Raises WireError (with its kind) unless the batch is what was asked for and fits the run. Frames are
    decompressed when used (TraceBatch.observations_array raises WireError for a corrupt one)."""
    if (batch.batch_size, batch.trace_length) != (batch_size, trace_length):
        raise _misfit("batch_shape", f"TraceBatch: {batch.batch_size} traces of {batch.trace_length} steps, "
                                     f"asked for {batch_size} of {trace_length}")
    _check_steps(np.asarray(batch.actions), np.asarray(batch.rewards), batch.observations, shape, "TraceBatch")
    _check_state_rows(batch.initial_state, batch_size, shape, "TraceBatch.initial_state")


def _check_state_rows(rows: np.ndarray, count: int, shape: RunShape, what: str) -> None:
    """A run with stored states needs one (2, state_units) row per step or trace; a run without ignores rows."""
    if shape.state_units and np.shape(rows) != (count, 2, shape.state_units):
        raise _misfit("recurrent_state", f"{what}: shape {list(np.shape(rows))}, the run stores LSTM states "
                                         f"(learner.stored_state) as [{count}, 2, {shape.state_units}]")


def stat_number(values: Any, name: str, *, integer: bool = False, minimum: float = -math.inf,
                maximum: float = math.inf) -> float | int | None:
    """values[name] when it is a finite number within [minimum, maximum] (and integral if asked),
    else None: a row's value read without trusting that it is there or what it is."""
    value = values.get(name) if isinstance(values, dict) else None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    if isinstance(value, float) and not math.isfinite(value) or not minimum <= value <= maximum:
        return None
    if integer:
        if value != int(value):
            return None
        return int(value)
    return value
