"""The messages the roles exchange: one dataclass per type, whose fields name their codec
(common/wire/codecs.py); ``check`` holds the rules that span fields. ``MESSAGE_TYPES`` is every type the
envelope (common/wire/envelope.py) knows, by class name: the name travels, so it must not change.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from common.wire.codecs import (COUNT, DTYPES, PROBABILITY, Array, Flag, Frames, Integer, Message, Nested, Nullable,
                                NumberDict, Real, TensorDict, Text, wired)
from common.wire.state_rows import no_states
from common.wire.errors import WireError
from common.wire.frames import FrameStack
from common.wire.exploration_state import ExplorationState
from common.wire.metrics import ActorStats, LearnerStats
from common.wire.weights_encoding import WEIGHTS_ENCODINGS, decode_tensor, encode_tensor


STATES = Array("float16", 3, finite=True, dtypes=("float16",))  # LSTM state rows (n, 2, lstm_units)


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
    # Episodes the actor can have in hand past those it delivered (its envs_per_actor + queue_episodes),
    # for the replay's hold guard; 0: not stated (older senders), the run's config's then.
    in_hand: int = wired(COUNT, default=0)
    # learner.stored_state: the LSTM state (h, c) before each step, [L, 2, lstm_units]; (0, 2, 0) when not
    # recorded (common/wire/state_rows.py)
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
    # replay that died since its last save) makes the replay count them served; one further below it
    # than the learner can hold (common.pacing.learner_stock) re-owes replies that never reached it.
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
class Stats(Message):
    """Untyped counters: the recorder's (their names follow the keys it records), and the form older learners,
    actors and replays wrote theirs in (a learner's or an actor's decodes into its typed message)."""

    source: str = wired(Text())
    time: float = wired(Real())
    values: dict[str, int | float | str] = wired(NumberDict(text=True))


HOLD_REASONS = ("", "behind", "budget")  # why the rate limiter holds actors; "": it does not


@dataclass(eq=False)
class RateState(Message):
    """The replay's rate limiter (replay/rate_limiter.py), the one authority on the pace: its counters and
    decisions, on replay/rate when the actors' hold changes and every stats period, and inside ReplayStats."""
    time: float = wired(Real())
    env_steps: int = wired(COUNT)  # every step received, stored or not
    batches_served: int = wired(COUNT)  # since updates started: the learner's updates
    updates_due: float = wired(Real(min_value=0.0))  # what the steps since the start mark pay for
    start_env_steps: float | None = wired(Nullable(Real(min_value=0.0)))  # the start mark; None: not started
    hold_reason: str = wired(Text())  # one of HOLD_REASONS
    closed: bool = wired(Flag())  # budget spent and paid for: the run takes no more episodes
    refilling: bool = wired(Flag())  # a resumed replay refilling its store: updates wait
    refill_env_steps: int = wired(COUNT)
    lost_updates: int = wired(COUNT)  # served and never trained on (the learner died, the reply was lost): owed again
    recounted_updates: int = wired(COUNT)  # made by a learner, lost from a resumed replay's counters
    error_buffer_updates: float = wired(Real(min_value=1.0))  # B: how far the learner may run ahead
    hold_updates: float = wired(Real(min_value=0.0))  # how far it may fall behind before actors hold
    env_steps_per_update_target: float = wired(Real(min_value=0.0))
    env_steps_per_update: float | None = wired(Nullable(Real()))  # achieved; None before the first batch
    unpaced: bool = wired(Flag(), default=False)  # B holds nobody: the run closes at its budget, the rest unpaid

    @property
    def updates_started(self) -> bool:
        """Batches are served: past the start mark and not refilling."""
        return self.start_env_steps is not None and not self.refilling

    def check(self) -> None:
        if self.hold_reason not in HOLD_REASONS:
            raise WireError(f"RateState.hold_reason: {self.hold_reason!r} is not one of {HOLD_REASONS}")
        if self.start_env_steps is not None and self.start_env_steps > self.env_steps:
            raise WireError(f"RateState.start_env_steps: {self.start_env_steps} lies past env_steps "
                            f"{self.env_steps}")
        if self.start_env_steps is None and self.batches_served:
            raise WireError(f"RateState: {self.batches_served} batches served before updates started")


@dataclass(eq=False)
class BufferFillState(Message):
    """The random phase's share of what the replay holds and serves, and its first fill (replay/buffer_fill.py)."""
    held_random_steps: int = wired(COUNT, default=0)  # stored steps acted without trained weights
    sampled_batches: int = wired(COUNT, default=0)  # batches the sample counters cover
    sampled_steps: int = wired(COUNT, default=0)
    sampled_random_steps: int = wired(COUNT, default=0)
    full_at_env_steps: int = wired(COUNT, default=0)  # when the store first held replay.capacity episodes; 0: never
    full_at_batches: int = wired(COUNT, default=0)
    sampled_steps_after_full: int = wired(COUNT, default=0)
    sampled_random_steps_after_full: int = wired(COUNT, default=0)


@dataclass(eq=False)
class ReplayStats(Message):
    """The replay's counters, on replay/stats every replay.stats_period_s (replay/process.py)."""
    time: float = wired(Real())
    episodes: int = wired(COUNT)  # stored now
    frames: int = wired(COUNT)
    bytes: int = wired(COUNT)
    env_steps_total: int = wired(COUNT)  # steps of every episode taken
    inserted: int = wired(COUNT)
    evicted: int = wired(COUNT)
    evicted_for_budget: int = wired(COUNT)
    short_dropped: int = wired(COUNT)  # episodes too short for a trace
    traces_served: int = wired(COUNT)
    pending_requests: int = wired(COUNT)
    rejected_requests: int = wired(COUNT)
    expired_requests: int = wired(COUNT)
    failed_samples: int = wired(COUNT)
    episodes_missing: int = wired(COUNT)  # episode indices that never arrived (replay/ledger.py)
    episode_sources: int = wired(COUNT)  # actor processes heard from
    restored_episodes: int = wired(COUNT)
    restore_skipped: int = wired(COUNT)
    late_episodes: int = wired(COUNT)  # arrived after the run closed: not taken
    late_env_steps: int = wired(COUNT)
    snapshot_age_s: float | None = wired(Nullable(Real()))  # None: no snapshot taken yet
    frame_bytes_mean: float | None = wired(Nullable(Real(min_value=0.0)))  # None: the store is empty
    rate: RateState = wired(Nested(RateState))
    snapshot: dict[str, int | float] = wired(NumberDict())  # snapshots_written, snapshot_failures, ...
    rejected: dict[str, int | float] = wired(NumberDict())  # rejected_<kind>, malformed_<door>, rejected_total
    speeds: dict[str, int | float] = wired(NumberDict())  # <counter>_per_s over the last period
    # absent from the stats of replays that predate it
    fill: BufferFillState = wired(Nested(BufferFillState), default_factory=BufferFillState)


# the messages of counters that logs keep as flat rows (Stats: the untyped form of older senders' logs)
COUNTER_TYPES = (Stats, LearnerStats, ActorStats, RateState, ReplayStats)


def flat_values(message: Message) -> dict[str, int | float | str]:
    """A counters message as one flat row, the shape logs and CSVs keep: a Stats' values; a typed message's
    fields, a nested message's named with its field's prefix, a dict's merged, flags as 0 or 1, None left out."""
    if isinstance(message, Stats):
        return dict(message.values)
    flat: dict[str, int | float | str] = {}
    for field in dataclasses.fields(message):
        value = getattr(message, field.name)
        if isinstance(value, Message):
            flat.update({f"{field.name}_{name}": item for name, item in flat_values(value).items()})
        elif isinstance(value, dict):
            flat.update(value)
        elif value is not None:
            flat[field.name] = int(value) if isinstance(value, bool) else value
    return flat


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
    # Actions that were not argmax Q of the weights acting: what the strategy explored, whatever its epsilon
    # says (a softmax sample is often the greedy action). -1: not counted (an action taken without Q-values,
    # in the random phase, or an older actor).
    off_greedy: int = wired(Integer(min_value=-1), default=-1)

    def check(self) -> None:
        if self.off_greedy > self.length:
            raise WireError(f"EpisodeRecord: {self.off_greedy} off-greedy actions in {self.length} steps")


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


MAX_PIECE_BYTES = 1 << 20  # a piece this large fits a fast link's queue; actors ask for far less


@dataclass(eq=False)
class WeightsPieceAsk(Message):
    """An actor's ask for a piece of the learner's weights (actor.weights_download): the bytes from
    `offset` of the encoded Weights of `version` (-1: the latest), at most `size` of them."""
    version: int = wired(Integer(min_value=-1))
    offset: int = wired(COUNT)
    size: int = wired(Integer(min_value=1, max_value=MAX_PIECE_BYTES))


@dataclass(eq=False)
class WeightsPiece(Message):
    """A piece of the encoded Weights message of `version`, which is `total_bytes` long: its bytes from
    `offset`. An actor on a slow link asks for the next piece once one has come, so no queue on the way
    holds more than a piece (learner/weights_shelf.py, actor/weights_download.py)."""
    version: int = wired(COUNT)
    total_bytes: int = wired(Integer(min_value=1))
    offset: int = wired(COUNT)
    data: np.ndarray = wired(Array("uint8", 1))

    def check(self) -> None:
        if len(self.data) > MAX_PIECE_BYTES:
            raise WireError(f"WeightsPiece: {len(self.data)} bytes, more than a piece may hold ({MAX_PIECE_BYTES})")
        if self.offset + len(self.data) > self.total_bytes or not len(self.data):
            raise WireError(f"WeightsPiece: bytes {self.offset}..{self.offset + len(self.data)} do not lie within "
                            f"the {self.total_bytes} of the weights")


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.__name__: cls
    for cls in (Episode, TraceBatchRequest, TraceBatch, Weights, ExplorationState, Stats, LearnerStats, ActorStats,
                EpisodeRecord, EpisodeAck, RateState, ReplayStats, WeightsPieceAsk, WeightsPiece)
}
