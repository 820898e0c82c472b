"""The messages the roles exchange: one dataclass per type, whose fields name their codec
(common/wire/codecs.py); ``check`` holds the rules that span fields. ``MESSAGE_TYPES`` is every type the
envelope (common/wire/envelope.py) knows, by class name: the name travels, so it must not change.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from common.wire.codecs import (DTYPES, Array, Flag, Frames, Integer, Message, Nullable, NumberDict, PlainDict,
                                Real, TensorDict, Text, wired)
from common.stored_state import no_states
from common.wire.errors import WireError
from common.wire.frames import FrameStack
from common.wire.weights_encoding import WEIGHTS_ENCODINGS, decode_tensor, encode_tensor


PROBABILITY = Real(0.0, 1.0)
STATES = Array("float16", 3, finite=True, dtypes=("float16",))  # LSTM state rows (n, 2, lstm_units)
COUNT = Integer(min_value=0)


@dataclass(eq=False)
class Episode(Message):
    observations: FrameStack = wired(Frames())  # L + 1 frames
    actions: np.ndarray = wired(Array("int64", 1))  # [L]
    rewards: np.ndarray = wired(Array("float32", 1, finite=True))  # [L]
    terminated: bool = wired(Flag())  # ended by a terminal state
    truncated: bool = wired(Flag())  # cut by the step limit
    actor_id: int = wired(COUNT)
    start_set: str = wired(Text())
    start_index: int = wired(COUNT)
    weights_version: np.ndarray = wired(Array("int64", 1))  # [L] version each step was acted with
    epsilon: float = wired(PROBABILITY)
    seed: int = wired(Integer())
    episode_index: int = wired(COUNT)  # per actor process, from 0
    # A random number per actor process: (actor_id, incarnation, episode_index) names an episode, so the
    # replay stores none twice and counts the indices that never arrived. 0: unnamed (older senders).
    incarnation: int = wired(COUNT, default=0)
    # learner.stored_state: the LSTM state (h, c) before each step, [L, 2, lstm_units]; (0, 2, 0) when not
    # recorded (common/stored_state.py)
    recurrent_state: np.ndarray = wired(STATES, default_factory=no_states)

    def __len__(self) -> int:
        return len(self.actions)

    def check(self) -> None:
        steps = len(self.actions)
        if steps < 1:
            raise WireError("Episode: an episode has at least one step")
        if len(self.observations) != steps + 1:
            raise WireError(f"Episode: {len(self.observations)} observations for {steps} steps (need steps + 1)")
        for name in ("rewards", "weights_version"):
            if np.shape(getattr(self, name)) != (steps,):
                raise WireError(f"Episode.{name}: shape {np.shape(getattr(self, name))}, expected ({steps},)")
        if np.min(self.actions) < 0:
            raise WireError("Episode.actions: negative action index")
        _check_state_rows(self.recurrent_state, steps, "Episode.recurrent_state")


def _check_state_rows(rows: np.ndarray, expected: int, where: str) -> None:
    """State rows are absent, (0, 2, 0), or one (2, units) row per step or trace."""
    shape = np.shape(rows)
    if shape != (0, 2, 0) and (shape[0] != expected or shape[1] != 2 or shape[2] < 1):
        raise WireError(f"{where}: shape {shape}, expected ({expected}, 2, lstm_units) or (0, 2, 0) for none")


@dataclass(eq=False)
class TraceBatchRequest(Message):
    request_id: int = wired(Integer())
    batch_size: int = wired(Integer(min_value=1))
    trace_length: int = wired(Integer(min_value=1))
    # The updates the learner has made. A learner process's first request (request_id 0) states the
    # updates it starts from (its checkpoint's, 0 when fresh): the replay owes again the batches a killed
    # learner never kept. A later one stating more than the replay counts served (counters lost with a
    # replay that died since its last save) makes the replay count them served.
    learner_updates: int = wired(Integer(min_value=-1), default=-1)  # -1: not stated


@dataclass(eq=False)
class TraceBatch(Message):
    request_id: int = wired(Integer())
    observations: FrameStack = wired(Frames())  # B * (T + 1) frames, row-major by trace
    actions: np.ndarray = wired(Array("int64", 2))  # [B, T]
    rewards: np.ndarray = wired(Array("float32", 2, finite=True))  # [B, T]
    terminated: np.ndarray = wired(Array("bool", 2))  # [B, T] True only where a terminal state ended the episode
    weights_version: np.ndarray = wired(Array("int64", 2))  # [B, T]
    env_steps_total: int = wired(COUNT)  # frames the replay has received, for the learner's ratio control
    episodes_stored: int = wired(COUNT)
    # learner.stored_state: each trace's LSTM state before its first step, [B, 2, lstm_units]; (0, 2, 0): none
    initial_state: np.ndarray = wired(STATES, default_factory=no_states)

    @property
    def batch_size(self) -> int:
        return np.shape(self.actions)[0]

    @property
    def trace_length(self) -> int:
        return np.shape(self.actions)[1]

    def observations_array(self) -> np.ndarray:
        """Decoded observations [B, T + 1, H, W, C]."""
        frames = self.observations.decode()
        return frames.reshape(self.batch_size, self.trace_length + 1, *self.observations.frame_shape)

    def check(self) -> None:
        shape = np.shape(self.actions)
        if 0 in shape:
            raise WireError(f"TraceBatch: empty batch of shape {shape}")
        for name in ("rewards", "terminated", "weights_version"):
            if np.shape(getattr(self, name)) != shape:
                raise WireError(f"TraceBatch.{name}: shape {np.shape(getattr(self, name))}, expected {shape}")
        batch, steps = shape
        if len(self.observations) != batch * (steps + 1):
            raise WireError(f"TraceBatch: {len(self.observations)} observations for {batch} traces of {steps} steps "
                            f"(need {batch * (steps + 1)})")
        if np.asarray(self.terminated)[:, :-1].any():
            raise WireError("TraceBatch.terminated: a terminal state before a trace's last step "
                            "(traces never cross an episode end)")
        _check_state_rows(self.initial_state, batch, "TraceBatch.initial_state")


@dataclass(eq=False)
class Weights(Message):
    version: int = wired(Integer())
    tensors: dict[str, np.ndarray] = wired(TensorDict())  # in the encoding's dtype
    created: float | None = wired(Nullable(Real()), default=None)  # time.time() at the learner
    encoding: str = wired(Text(), default="float32")  # one of WEIGHTS_ENCODINGS; absent: an older sender's float32

    @classmethod
    def from_float32(cls, version: int, tensors: dict[str, np.ndarray], encoding: str = "float32",
                     created: float | None = None) -> Weights:
        """The message of float32 tensors in the given encoding; WireError (kind "weights_encoding") for an
        unknown encoding or a value the encoding cannot hold (float16 beyond +-65504)."""
        if encoding not in WEIGHTS_ENCODINGS:
            raise WireError(f"Weights: unknown encoding {encoding!r}; known: {', '.join(WEIGHTS_ENCODINGS)}",
                            "weights_encoding")
        encoded = {name: encode_tensor(np.asarray(array, dtype=np.float32), encoding, name)
                   for name, array in tensors.items()}
        return cls(version=version, tensors=encoded, created=created, encoding=encoding)

    def to_float32(self) -> dict[str, np.ndarray]:
        """The tensors widened to float32 (a float32 message's own arrays as they came, read-only); WireError
        (kind "weights_encoding") for an encoding this build does not know or tensors not in its dtype."""
        self._check_encoding()
        if self.encoding == "float32":
            return dict(self.tensors)
        return {name: decode_tensor(np.asarray(array), self.encoding) for name, array in self.tensors.items()}

    def check(self) -> None:
        if self.encoding in WEIGHTS_ENCODINGS:
            self._check_encoding()

    def _check_encoding(self) -> None:
        if self.encoding not in WEIGHTS_ENCODINGS:
            raise WireError(f"Weights version {self.version}: unknown encoding {self.encoding!r}; this build reads "
                            f"{', '.join(WEIGHTS_ENCODINGS)}", "weights_encoding")
        dtype = WEIGHTS_ENCODINGS[self.encoding]
        allowed = DTYPES if dtype is None else (dtype,)
        for name, array in self.tensors.items():
            if np.asarray(array).dtype.name not in allowed:
                raise WireError(f"Weights.tensors.{name}: dtype {np.asarray(array).dtype} is not one of "
                                f"{', '.join(allowed)} (encoding {self.encoding})", "weights_encoding")


@dataclass(eq=False)
class ExplorationState(Message):
    strategy: str = wired(Text())
    params: dict[str, Any] = wired(PlainDict())
    epsilon: float = wired(PROBABILITY)
    kappa: float = wired(Real(min_value=0.0))  # 0 when the strategy has no temperature
    started: bool = wired(Flag())  # before updates start every strategy acts uniformly
    counters: dict[str, int | float] = wired(NumberDict())
    state: dict[str, Any] = wired(PlainDict())  # the strategy's own serialisable state


@dataclass(eq=False)
class Stats(Message):
    source: str = wired(Text())
    time: float = wired(Real())
    values: dict[str, int | float | str] = wired(NumberDict(text=True))


@dataclass(eq=False)
class EpisodeRecord(Message):
    actor_id: int = wired(COUNT)
    episode_index: int = wired(COUNT)
    length: int = wired(COUNT)
    episode_return: float = wired(Real())
    collided: bool = wired(Flag())
    start_set: str = wired(Text())
    start_index: int = wired(COUNT)
    epsilon: float = wired(PROBABILITY)
    weights_version: int = wired(Integer())
    wall_time: float = wired(Real(min_value=0.0))  # seconds the episode took
    time: float = wired(Real())


@dataclass(eq=False)
class Heartbeat(Message):
    role: str = wired(Text())
    process_id: str = wired(Text())
    time: float = wired(Real())
    seq: int = wired(COUNT)


MAX_ACK_INDICES = 65_536  # indices in one EpisodeAck: far more than an actor has in flight


@dataclass(eq=False)
class EpisodeAck(Message):
    """The replay's word on episodes of one actor process (actor_id, incarnation), by episode index:
    received (it holds them: stop resending), kept (held durably, in a snapshot or in memory when
    snapshots are off: forget them) or refused (never taken, a malformed episode or a closed run:
    forget them too). Delivery that survives partitions and replay restarts (actor/delivery.py)."""
    actor_id: int = wired(COUNT)
    incarnation: int = wired(COUNT)
    received: np.ndarray = wired(Array("int64", 1))
    kept: np.ndarray = wired(Array("int64", 1))
    refused: np.ndarray = wired(Array("int64", 1))

    def check(self) -> None:
        for name in ("received", "kept", "refused"):
            indices = getattr(self, name)
            if len(indices) > MAX_ACK_INDICES:
                raise WireError(f"EpisodeAck.{name}: {len(indices)} indices, at most {MAX_ACK_INDICES}")
            if len(indices) and np.min(indices) < 0:
                raise WireError(f"EpisodeAck.{name}: a negative episode index")


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.__name__: cls
    for cls in (Episode, TraceBatchRequest, TraceBatch, Weights, ExplorationState, Stats, EpisodeRecord, Heartbeat,
                EpisodeAck)
}
