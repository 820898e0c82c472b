"""The codec of each kind of field of a message: it writes the field to msgpack-ready values and checks
it when reading, so that decoding validates everything and any malformed input raises ``WireError``.

Each message type (common/wire/messages.py) is a dataclass of ``Message`` whose fields name their codec
(``wired``). Arrays travel as ``{"dtype", "shape", "data"}`` with little-endian raw bytes. Decoded arrays
are read-only views of the received buffer (no copy of a 50 MB weights message); copy one before writing
into it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from common.wire.errors import WireError
from common.wire.frames import MAX_FRAME_BYTES, FrameStack

DTYPES = ("uint8", "bool", "int32", "int64", "float32", "float64")
WEIGHTS_DTYPES = DTYPES + ("float16", "uint16")  # what weights tensors may travel in (common/wire/weights_encoding.py)
MAX_ARRAY_NDIM = 32
INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1


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


def _check_key(key: Any, where: str) -> str:
    if not isinstance(key, str):
        raise _fail(where, f"keys must be strings, got {key!r}")
    return key


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
class Counts(NumberDict):
    """str -> a non-negative integer: counters whose names are made at run time (a rejection's kind, a door)."""

    def unpack(self, raw, where):
        if not isinstance(raw, dict):
            raise _fail(where, f"expected a dict, got {_type_name(raw)}")
        for key, item in raw.items():
            COUNT.unpack(item, f"{where}.{_check_key(key, where)}")
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
PROBABILITY = Real(0.0, 1.0)
COUNT = Integer(min_value=0)


def wired(codec: Codec, **kwargs: Any) -> Any:
    """A dataclass field carrying the codec that writes and checks it."""
    return field(metadata={"codec": codec}, **kwargs)


class Dependent(Codec):
    """A field whose codec the message's other fields choose (they are read first): the strategy an
    ExplorationState names decides what its params and its state are (common/wire/exploration_state.py)."""

    def given(self, values: dict[str, Any], where: str) -> Codec:
        """The codec for these values of the other fields; WireError if they choose none."""
        raise NotImplementedError

    def pack(self, value, where):
        raise _fail(where, "a dependent field is written by the codec its message's other fields choose")

    unpack = pack


class Message:
    """Base of the wire messages; ``check`` holds the rules that span fields. ``former_types``: the types an
    older sender wrote it as, which decode into it (common/wire/envelope.py)."""

    former_types: ClassVar[tuple[str, ...]] = ()

    def check(self) -> None:
        pass


def field_codecs(cls: type[Message]) -> list[tuple[str, Codec]]:
    return [(f.name, f.metadata["codec"]) for f in dataclasses.fields(cls)]


def pack_fields(message: Message, where: str) -> dict[str, Any]:
    """The message's fields as msgpack-ready values, each checked by its codec, then the message's check."""
    values = {name: getattr(message, name) for name, _ in field_codecs(type(message))}
    fields = {name: _chosen(codec, values, f"{where}.{name}").pack(values[name], f"{where}.{name}")
              for name, codec in field_codecs(type(message))}
    message.check()
    return fields


def unpack_fields(cls: type[Message], fields: Any, where: str) -> Message:
    """The message of type cls from its packed fields, every field and the message checked."""
    if not isinstance(fields, dict):
        raise _fail(where, "fields must be a map")
    codecs = field_codecs(cls)
    names = {name for name, _ in codecs}
    defaulted = {f.name for f in dataclasses.fields(cls)
                 if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING}
    missing, extra = names - set(fields) - defaulted, set(fields) - names
    if missing:
        raise _fail(where, f"missing field(s) {', '.join(sorted(missing))}")
    if extra:
        raise _fail(where, f"unexpected field(s) {', '.join(sorted(map(str, extra)))}")
    # a field with a default may be absent: messages of senders that predate it still decode
    values = {name: codec.unpack(fields[name], f"{where}.{name}") for name, codec in codecs
              if name in fields and not isinstance(codec, Dependent)}
    values.update({name: codec.given(values, f"{where}.{name}").unpack(fields[name], f"{where}.{name}")
                   for name, codec in codecs if name in fields and isinstance(codec, Dependent)})
    message = cls(**values)
    message.check()
    return message


def _chosen(codec: Codec, values: dict[str, Any], where: str) -> Codec:
    return codec.given(values, where) if isinstance(codec, Dependent) else codec


@dataclass(frozen=True)
class Nested(Codec):
    """A message of the given type inside another, written as the map of its fields."""

    cls: type

    def pack(self, value, where):
        if type(value) is not self.cls:
            raise _fail(where, f"expected a {self.cls.__name__}, got {_type_name(value)}")
        return pack_fields(value, where)

    def unpack(self, raw, where):
        return unpack_fields(self.cls, raw, where)
