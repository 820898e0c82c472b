"""Every message the roles exchange, and its one msgpack encoding.

An encoded message is a msgpack map ``{"schema": SCHEMA_VERSION, "type": <class
name>, "fields": {...}}``. Each message type is a dataclass whose fields name
their codec; the codec both writes the field and checks it when reading, so
``decode`` validates everything and any malformed input raises ``WireError``.

Arrays travel as ``{"dtype", "shape", "data"}`` with little-endian raw bytes.
Decoded arrays are read-only views of the received buffer (no copy of a 50 MB
weights message); copy one before writing into it.

Image frames travel as a ``FrameStack``: one zstd blob per frame, so the replay
keeps episodes compressed and builds trace replies from the stored blobs
without recompressing, and a reader decodes only the frames it needs.
``decode`` checks each blob's zstd header (declared size = frame size) but does
not decompress; ``FrameStack.decode`` and ``FrameStack.verify`` do, and raise
WireError for a blob whose content is corrupt.

A message that decodes can still not fit the run: frames of another size, actions
outside the action space, absurd rewards. ``RunShape`` holds what a run's messages
must fit, ``check_episode`` and ``check_trace_batch`` check it (every frame of an
episode is decompressed), and ``stat_number`` reads one value of a Stats message
without trusting it. Each WireError has a ``kind`` (a short name for counting), and
``Rejections`` counts refused input by kind and logs it at a bounded rate.

Weights travel whole (``encoding`` "float32") or compact, at half the size: "float16", or
"bfloat16" (float32's upper half, float32's range; numpy has no bfloat16, so its bit patterns
travel as uint16). ``Weights.from_float32`` makes either, ``Weights.to_float32`` reads any. A
known encoding whose tensors are of another dtype does not decode; an unknown one (a newer
sender's) does, and ``to_float32`` refuses it (kind "weights_encoding") for the reader to count.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Iterable, Sequence

import msgpack
import numpy as np
import zstandard

SCHEMA_VERSION = 1

DTYPES = ("uint8", "bool", "int32", "int64", "float32", "float64")
# encoding -> the dtype its tensors travel in; float32 messages keep any of DTYPES, as before encodings
WEIGHTS_ENCODINGS = {"float32": None, "float16": "float16", "bfloat16": "uint16"}
WEIGHTS_DTYPES = DTYPES + ("float16", "uint16")
ZSTD_LEVEL = 1  # frames are flat-shaded renderings; higher levels buy little and cost time
MAX_FRAME_BYTES = 16 * 2**20  # a declared frame larger than this is refused before decompressing
MAX_ARRAY_NDIM = 32
MAX_PLAIN_DEPTH = 32
INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1


class WireError(ValueError):
    """A message cannot be encoded or decoded, or does not fit the run; the text names the field
    and the fault, ``kind`` names the fault for counting ("undecodable", "wrong_type", "invalid",
    or a RunShape check's kind such as "frame_shape" or "actions")."""

    def __init__(self, text: str, kind: str = "invalid") -> None:
        super().__init__(text)
        self.kind = kind


# --- frames ----------------------------------------------------------------------

_zstd = threading.local()  # zstd contexts are not thread-safe; zenoh calls back on its own threads


def _compressor() -> zstandard.ZstdCompressor:
    if not hasattr(_zstd, "compressor"):
        _zstd.compressor = zstandard.ZstdCompressor(level=ZSTD_LEVEL, write_checksum=True, write_content_size=True)
    return _zstd.compressor


def _decompressor() -> zstandard.ZstdDecompressor:
    if not hasattr(_zstd, "decompressor"):
        _zstd.decompressor = zstandard.ZstdDecompressor()
    return _zstd.decompressor


class FrameStack:
    """A sequence of uint8 frames of one shape, each stored as its own zstd blob."""

    def __init__(self, blobs: Sequence[bytes], frame_shape: Sequence[int]):
        self.blobs: list[bytes] = list(blobs)
        self.frame_shape: tuple[int, ...] = tuple(int(n) for n in frame_shape)

    @classmethod
    def from_array(cls, frames: np.ndarray) -> FrameStack:
        """Compresses frames [n, H, W, C] (uint8), one blob per frame."""
        frames = np.asarray(frames)
        if frames.dtype != np.uint8 or frames.ndim != 4:
            raise WireError(f"FrameStack.from_array: expected uint8 frames [n, H, W, C], got {frames.dtype} {frames.shape}")
        compressor = _compressor()
        blobs = [compressor.compress(np.ascontiguousarray(frame)) for frame in frames]
        return cls(blobs, frames.shape[1:])

    @classmethod
    def concat(cls, stacks: Iterable[FrameStack]) -> FrameStack:
        """One stack holding the frames of all stacks in order (the blobs are shared)."""
        stacks = list(stacks)
        if not stacks:
            raise WireError("FrameStack.concat: no stacks given")
        shapes = {stack.frame_shape for stack in stacks}
        if len(shapes) != 1:
            raise WireError(f"FrameStack.concat: frame shapes differ: {sorted(shapes)}")
        return cls([blob for stack in stacks for blob in stack.blobs], stacks[0].frame_shape)

    def __len__(self) -> int:
        return len(self.blobs)

    def __repr__(self) -> str:
        return f"FrameStack({len(self)} frames of {self.frame_shape}, {self.nbytes} bytes compressed)"

    @property
    def nbytes(self) -> int:
        return sum(len(blob) for blob in self.blobs)

    @property
    def frame_bytes(self) -> int:
        return math.prod(self.frame_shape)

    def select(self, indices: Iterable[int]) -> FrameStack:
        """The frames at the given indices, sharing the blob objects (no recompression)."""
        return FrameStack([self.blobs[i] for i in indices], self.frame_shape)

    def decode(self, start: int = 0, stop: int | None = None) -> np.ndarray:
        """Frames[start:stop] as uint8 [n, H, W, C]; only those blobs are decompressed."""
        positions = range(len(self.blobs))[start:stop]
        out = np.empty((len(positions), *self.frame_shape), dtype=np.uint8)
        for row, position in enumerate(positions):
            out[row] = self._decompress(position).reshape(self.frame_shape)
        return out

    def verify(self) -> None:
        """Decompresses every blob once; raises WireError if any is corrupt."""
        for position in range(len(self.blobs)):
            self._decompress(position)

    def check_headers(self) -> None:
        """Checks that every blob is a zstd frame declaring one frame's size, without decompressing."""
        for position in range(len(self.blobs)):
            self._check_header(position)

    def _check_header(self, position: int) -> None:
        # The zstd frame header states the decompressed size: checking it first
        # refuses wrong shapes and garbage before any buffer is allocated.
        try:
            declared = zstandard.get_frame_parameters(self.blobs[position]).content_size
        except zstandard.ZstdError as error:
            raise WireError(f"frame {position}: not a zstd frame ({error})") from None
        if declared != self.frame_bytes:
            raise WireError(f"frame {position}: blob declares {declared} bytes, shape {self.frame_shape} needs {self.frame_bytes}")

    def _decompress(self, position: int) -> np.ndarray:
        try:
            self._check_header(position)
        except WireError as error:
            raise WireError(str(error), "frames_corrupt") from None
        blob = self.blobs[position]
        expected = self.frame_bytes
        try:
            raw = _decompressor().decompress(blob, max_output_size=expected, allow_extra_data=False)
        except zstandard.ZstdError as error:
            raise WireError(f"frame {position}: bad zstd blob ({error})", "frames_corrupt") from None
        if len(raw) != expected:
            raise WireError(f"frame {position}: decompressed to {len(raw)} bytes, expected {expected} for shape "
                            f"{self.frame_shape}", "frames_corrupt")
        return np.frombuffer(raw, dtype=np.uint8)


# --- codecs: one per kind of field -------------------------------------------------

class Codec:
    """Writes one field to msgpack-ready values and reads it back, checking it."""

    def pack(self, value: Any, where: str) -> Any:
        raise NotImplementedError

    def unpack(self, raw: Any, where: str) -> Any:
        raise NotImplementedError


def _fail(where: str, problem: str) -> WireError:
    return WireError(f"{where}: {problem}")


def _type_name(value: Any) -> str:
    return type(value).__name__


@dataclass(frozen=True)
class Integer(Codec):
    min_value: int = INT64_MIN
    max_value: int = INT64_MAX

    def pack(self, value, where):
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
            raise _fail(where, f"expected an integer, got {_type_name(value)}")
        return self.unpack(int(value), where)

    def unpack(self, raw, where):
        if isinstance(raw, bool) or not isinstance(raw, int):
            raise _fail(where, f"expected an integer, got {_type_name(raw)}")
        if not self.min_value <= raw <= self.max_value:
            raise _fail(where, f"{raw} is outside [{self.min_value}, {self.max_value}]")
        return raw


@dataclass(frozen=True)
class Real(Codec):
    min_value: float = -math.inf
    max_value: float = math.inf
    finite: bool = True

    def pack(self, value, where):
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise _fail(where, f"expected a number, got {_type_name(value)}")
        return self.unpack(float(value), where)

    def unpack(self, raw, where):
        if not isinstance(raw, float):
            raise _fail(where, f"expected a float, got {_type_name(raw)}")
        if self.finite and not math.isfinite(raw):
            raise _fail(where, f"must be finite, got {raw}")
        if not math.isnan(raw) and not self.min_value <= raw <= self.max_value:
            raise _fail(where, f"{raw} is outside [{self.min_value}, {self.max_value}]")
        return raw


@dataclass(frozen=True)
class Text(Codec):
    def pack(self, value, where):
        return self.unpack(value, where)

    def unpack(self, raw, where):
        if not isinstance(raw, str):
            raise _fail(where, f"expected a string, got {_type_name(raw)}")
        return raw


@dataclass(frozen=True)
class Flag(Codec):
    def pack(self, value, where):
        if isinstance(value, np.bool_):
            value = bool(value)
        return self.unpack(value, where)

    def unpack(self, raw, where):
        if not isinstance(raw, bool):
            raise _fail(where, f"expected a bool, got {_type_name(raw)}")
        return raw


@dataclass(frozen=True)
class Nullable(Codec):
    inner: Codec

    def pack(self, value, where):
        return None if value is None else self.inner.pack(value, where)

    def unpack(self, raw, where):
        return None if raw is None else self.inner.unpack(raw, where)


@dataclass(frozen=True)
class Array(Codec):
    """An ndarray of a whitelisted dtype; dtype and ndim are fixed unless None."""

    dtype: str | None = None
    ndim: int | None = None
    finite: bool = False  # reject NaN and inf in float arrays
    dtypes: tuple[str, ...] = DTYPES  # the dtypes it may hold when dtype is None

    def pack(self, value, where):
        try:
            array = np.asarray(value)
        except (ValueError, TypeError) as error:
            raise _fail(where, f"not an array ({error})") from None
        if self.dtype is not None and array.dtype != np.dtype(self.dtype):
            if not np.can_cast(array.dtype, self.dtype, "same_kind"):
                raise _fail(where, f"expected dtype {self.dtype}, got {array.dtype} (no same-kind cast)")
            array = array.astype(self.dtype)
        if array.dtype.name not in self.dtypes:
            raise _fail(where, f"dtype {array.dtype} is not one of {', '.join(self.dtypes)}")
        self._check_values(array, where)
        array = array.astype(array.dtype.newbyteorder("<"), order="C", copy=False)
        # A byte view avoids copying large tensors before msgpack copies them once.
        data = memoryview(array.reshape(-1)).cast("B") if array.size else b""
        return {"dtype": array.dtype.name, "shape": list(array.shape), "data": data}

    def unpack(self, raw, where):
        if not isinstance(raw, dict) or set(raw) != {"dtype", "shape", "data"}:
            raise _fail(where, "expected an array map with keys dtype, shape, data")
        dtype, shape, data = raw["dtype"], raw["shape"], raw["data"]
        if dtype not in self.dtypes:
            raise _fail(where, f"dtype {dtype!r} is not one of {', '.join(self.dtypes)}")
        if self.dtype is not None and dtype != self.dtype:
            raise _fail(where, f"expected dtype {self.dtype}, got {dtype}")
        if not isinstance(shape, list) or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape):
            raise _fail(where, f"shape must be a list of non-negative integers, got {shape!r}")
        if not isinstance(data, bytes):
            raise _fail(where, f"data must be bytes, got {_type_name(data)}")
        if len(shape) > MAX_ARRAY_NDIM:
            raise _fail(where, f"{len(shape)} dimensions, at most {MAX_ARRAY_NDIM} allowed")
        wire_dtype = np.dtype(dtype).newbyteorder("<")
        if math.prod(shape) * wire_dtype.itemsize != len(data):
            raise _fail(where, f"{len(data)} data bytes do not fill shape {shape} of {dtype}")
        array = np.frombuffer(data, dtype=wire_dtype).reshape(shape)
        if dtype == "bool" and array.size and array.view(np.uint8).max() > 1:
            raise _fail(where, "bool array holds bytes other than 0 and 1")
        self._check_values(array, where)
        return array

    def _check_values(self, array: np.ndarray, where: str) -> None:
        if self.dtype is not None and array.dtype != np.dtype(self.dtype):
            raise _fail(where, f"expected dtype {self.dtype}, got {array.dtype}")
        if self.ndim is not None and array.ndim != self.ndim:
            raise _fail(where, f"expected {self.ndim} dimensions, got shape {array.shape}")
        if self.finite and array.dtype.kind == "f" and not np.isfinite(array).all():
            raise _fail(where, "holds NaN or infinite values")


@dataclass(frozen=True)
class Frames(Codec):
    def pack(self, value, where):
        if not isinstance(value, FrameStack):
            raise _fail(where, f"expected a FrameStack, got {_type_name(value)}")
        self._check_shape(list(value.frame_shape), where)
        return {"shape": list(value.frame_shape), "blobs": value.blobs}

    def unpack(self, raw, where):
        if not isinstance(raw, dict) or set(raw) != {"shape", "blobs"}:
            raise _fail(where, "expected a frame map with keys shape, blobs")
        shape, blobs = raw["shape"], raw["blobs"]
        self._check_shape(shape, where)
        if not isinstance(blobs, list) or not all(isinstance(blob, bytes) for blob in blobs):
            raise _fail(where, "blobs must be a list of bytes")
        stack = FrameStack(blobs, shape)
        try:
            stack.check_headers()
        except WireError as error:
            raise _fail(where, str(error)) from None
        return stack

    @staticmethod
    def _check_shape(shape: Any, where: str) -> None:
        if not (isinstance(shape, list) and len(shape) == 3
                and all(isinstance(n, int) and not isinstance(n, bool) and n > 0 for n in shape)):
            raise _fail(where, f"frame shape must be three positive integers [H, W, C], got {shape!r}")
        if math.prod(shape) > MAX_FRAME_BYTES:
            raise _fail(where, f"frame shape {shape} exceeds {MAX_FRAME_BYTES} bytes")


def _check_plain(value: Any, where: str, depth: int = 0) -> Any:
    """A JSON-like value (None, bool, int, float, str, list, str-keyed dict) with numpy scalars unwrapped."""
    if depth > MAX_PLAIN_DEPTH:
        raise _fail(where, f"nested deeper than {MAX_PLAIN_DEPTH} levels")
    if isinstance(value, np.generic):
        value = value.item()
    if value is None or isinstance(value, (bool, float, str)):
        return value
    if isinstance(value, int):
        return Integer().unpack(value, where)
    if isinstance(value, list):
        return [_check_plain(item, f"{where}[{i}]", depth + 1) for i, item in enumerate(value)]
    if isinstance(value, dict):
        return {_check_key(key, where): _check_plain(item, f"{where}.{key}", depth + 1) for key, item in value.items()}
    raise _fail(where, f"{_type_name(value)} is not a plain value (None, bool, int, float, str, list, dict)")


def _check_key(key: Any, where: str) -> str:
    if not isinstance(key, str):
        raise _fail(where, f"keys must be strings, got {key!r}")
    return key


@dataclass(frozen=True)
class PlainDict(Codec):
    def pack(self, value, where):
        return self.unpack(value, where)

    def unpack(self, raw, where):
        if not isinstance(raw, dict):
            raise _fail(where, f"expected a dict, got {_type_name(raw)}")
        return _check_plain(raw, where)


@dataclass(frozen=True)
class NumberDict(Codec):
    """str -> int | float, or also str when ``text`` is set."""

    text: bool = False

    def pack(self, value, where):
        if isinstance(value, dict):
            value = {key: item.item() if isinstance(item, np.generic) else item for key, item in value.items()}
        return self.unpack(value, where)

    def unpack(self, raw, where):
        if not isinstance(raw, dict):
            raise _fail(where, f"expected a dict, got {_type_name(raw)}")
        allowed = (int, float, str) if self.text else (int, float)
        for key, item in raw.items():
            _check_key(key, where)
            if isinstance(item, bool) or not isinstance(item, allowed):
                kinds = "int, float or str" if self.text else "int or float"
                raise _fail(f"{where}.{key}", f"expected {kinds}, got {_type_name(item)}")
            if isinstance(item, int):
                Integer().unpack(item, f"{where}.{key}")
        return raw


@dataclass(frozen=True)
class TensorDict(Codec):
    """Named arrays of any whitelisted dtype and shape, floats finite."""

    def pack(self, value, where):
        return {name: _TENSOR.pack(array, f"{where}.{name}") for name, array in self._items(value, where)}

    def unpack(self, raw, where):
        return {name: _TENSOR.unpack(array, f"{where}.{name}") for name, array in self._items(raw, where)}

    @staticmethod
    def _items(value: Any, where: str):
        if not isinstance(value, dict):
            raise _fail(where, f"expected a dict of arrays, got {_type_name(value)}")
        for name in value:
            if not isinstance(name, str) or not name:
                raise _fail(where, f"tensor names must be non-empty strings, got {name!r}")
        return value.items()


_TENSOR = Array(finite=True, dtypes=WEIGHTS_DTYPES)


def wired(codec: Codec, **kwargs: Any) -> Any:
    """A dataclass field carrying the codec that writes and checks it."""
    return field(metadata={"codec": codec}, **kwargs)


# --- messages --------------------------------------------------------------------

class Message:
    """Base of the wire messages; ``check`` holds the rules that span fields."""

    def check(self) -> None:
        pass


PROBABILITY = Real(0.0, 1.0)
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
        encoded = {name: _encode_tensor(np.asarray(array, dtype=np.float32), encoding, name)
                   for name, array in tensors.items()}
        return cls(version=version, tensors=encoded, created=created, encoding=encoding)

    def to_float32(self) -> dict[str, np.ndarray]:
        """The tensors widened to float32 (a float32 message's own arrays as they came, read-only); WireError
        (kind "weights_encoding") for an encoding this build does not know or tensors not in its dtype."""
        self._check_encoding()
        if self.encoding == "float32":
            return dict(self.tensors)
        return {name: _decode_tensor(np.asarray(array), self.encoding) for name, array in self.tensors.items()}

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


FLOAT16_MAX = float(np.finfo(np.float16).max)


def _encode_tensor(array: np.ndarray, encoding: str, name: str) -> np.ndarray:
    if encoding == "float32":
        return array
    if encoding == "float16":
        with np.errstate(over="ignore"):  # beyond +-65504 rounds to infinity, refused here
            half = array.astype(np.float16)
        if not np.isfinite(half).all():
            raise WireError(f"Weights.tensors.{name}: a value of magnitude {float(np.abs(array).max()):.3g} is "
                            f"beyond float16's {FLOAT16_MAX:g}", "weights_encoding")
        return half
    # bfloat16: the upper 16 bits of each float32, rounded to nearest, ties to even
    if not np.isfinite(array).all():  # a NaN's bits could wrap round in the rounding below
        raise WireError(f"Weights.tensors.{name}: holds NaN or infinite values")
    bits = np.ascontiguousarray(array).view(np.uint32)
    rounded = bits >> np.uint32(16)
    rounded &= np.uint32(1)
    rounded += np.uint32(0x7FFF)
    rounded += bits
    rounded >>= np.uint32(16)
    upper = rounded.astype(np.uint16)
    if ((upper & np.uint16(0x7F80)) == np.uint16(0x7F80)).any():  # rounded up to infinity
        raise WireError(f"Weights.tensors.{name}: a value beyond bfloat16's range", "weights_encoding")
    return upper


def _decode_tensor(array: np.ndarray, encoding: str) -> np.ndarray:
    if encoding == "float16":
        return array.astype(np.float32)
    return (array.astype(np.uint32) << np.uint32(16)).view(np.float32)


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


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.__name__: cls
    for cls in (Episode, TraceBatchRequest, TraceBatch, Weights, ExplorationState, Stats, EpisodeRecord, Heartbeat)
}


# --- encode / decode -----------------------------------------------------------------

def _codecs(cls: type[Message]) -> list[tuple[str, Codec]]:
    return [(f.name, f.metadata["codec"]) for f in dataclasses.fields(cls)]


def _defaulted(cls: type[Message]) -> set[str]:
    return {f.name for f in dataclasses.fields(cls) if f.default is not dataclasses.MISSING}


def encode(message: Message) -> bytes:
    """The message as bytes; raises WireError if a field is invalid."""
    tag = type(message).__name__
    if MESSAGE_TYPES.get(tag) is not type(message):
        raise WireError(f"{tag} is not a wire message type")
    fields = {name: codec.pack(getattr(message, name), f"{tag}.{name}") for name, codec in _codecs(type(message))}
    message.check()
    return msgpack.packb({"schema": SCHEMA_VERSION, "type": tag, "fields": fields}, use_bin_type=True)


def decode(data: bytes, expected: type[Message] | None = None) -> Message:
    """The message in data, fully checked; expected, if given, is the required type."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise WireError(f"expected bytes, got {_type_name(data)}")
    try:
        envelope = msgpack.unpackb(data, raw=False, strict_map_key=True)
    except Exception as error:  # msgpack signals bad input with several exception types
        raise WireError(f"not a msgpack message ({type(error).__name__}: {error})", "undecodable") from None
    if not isinstance(envelope, dict) or set(envelope) != {"schema", "type", "fields"}:
        raise WireError("not a wire message: expected a map with keys schema, type, fields", "undecodable")
    if type(envelope["schema"]) is not int or envelope["schema"] != SCHEMA_VERSION:
        raise WireError(f"schema version {envelope['schema']!r} is not supported (this build reads version "
                        f"{SCHEMA_VERSION})", "undecodable")
    tag = envelope["type"]
    cls = MESSAGE_TYPES.get(tag) if isinstance(tag, str) else None
    if cls is None:
        raise WireError(f"unknown message type {tag!r}", "undecodable")
    if expected is not None and cls is not expected:
        raise WireError(f"expected message type {expected.__name__}, got {tag}", "wrong_type")
    return _build(cls, envelope["fields"])


def _build(cls: type[Message], fields: Any) -> Message:
    tag = cls.__name__
    if not isinstance(fields, dict):
        raise WireError(f"{tag}: fields must be a map")
    codecs = _codecs(cls)
    names = {name for name, _ in codecs}
    missing, extra = names - set(fields) - _defaulted(cls), set(fields) - names
    if missing:
        raise WireError(f"{tag}: missing field(s) {', '.join(sorted(missing))}")
    if extra:
        raise WireError(f"{tag}: unexpected field(s) {', '.join(sorted(map(str, extra)))}")
    # a field with a default may be absent: messages of senders that predate it still decode
    message = cls(**{name: codec.unpack(fields[name], f"{tag}.{name}") for name, codec in codecs if name in fields})
    message.check()
    return message


# --- does a message fit the run? -------------------------------------------------------------

@dataclass(frozen=True)
class RunShape:
    """What the messages of one run must fit, from its configuration."""

    frame_shape: tuple[int, int, int]  # H, W, C of every observation
    n_actions: int  # actions are indices in [0, n_actions)
    max_steps: int  # no episode is longer (env.max_steps)
    reward_limit: float  # |reward| above this is absurd (the env's rewards lie in [0, 1])

    @classmethod
    def of(cls, config: Any) -> RunShape:
        """The shape of a common.config.Config."""
        network = config.network
        return cls((network.frame_height, network.frame_width, network.frame_channels), network.n_actions,
                   config.env.max_steps, config.replay.reward_limit)


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


def stat_number(values: Any, name: str, *, integer: bool = False, minimum: float = -math.inf,
                maximum: float = math.inf) -> float | int | None:
    """values[name] when it is a finite number within [minimum, maximum] (and integral if asked),
    else None: a Stats value read without trusting that it is there or what it is."""
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


# --- counting what is refused -----------------------------------------------------------------

class Rejections:
    """Refused input by kind: counted, and logged at most once per kind per period (the next line
    of a kind says how many were not shown). Thread-safe: Zenoh calls back on several threads."""

    def __init__(self, logger: logging.Logger, period_s: float = 10.0, clock=time.monotonic) -> None:
        self._log = logger
        self._period_s = period_s
        self._clock = clock
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self._last: dict[str, float] = {}
        self._unshown: Counter[str] = Counter()

    def reject(self, kind: str, text: str) -> None:
        with self._lock:
            self.counts[kind] += 1
            now = self._clock()
            if now - self._last.get(kind, -math.inf) < self._period_s:
                self._unshown[kind] += 1
                return
            self._last[kind] = now
            unshown, self._unshown[kind] = self._unshown[kind], 0
        more = f" ({unshown} more of this kind since the last line)" if unshown else ""
        self._log.warning("rejected (%s): %s%s", kind, text[:500], more)

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self.counts.values())

    def values(self, prefix: str = "rejected_") -> dict[str, int]:
        """{prefix + kind: count} and {prefix + "total": sum}, for a Stats message."""
        with self._lock:
            counts = dict(self.counts)
        return {**{f"{prefix}{kind}": count for kind, count in sorted(counts.items())},
                f"{prefix}total": sum(counts.values())}
