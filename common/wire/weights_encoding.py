"""How weights travel: whole (``encoding`` "float32") or compact, at half the size: "float16", or
"bfloat16" (float32's upper half, float32's range; numpy has no bfloat16, so its bit patterns travel as
uint16). ``Weights.from_float32`` (common/wire/messages.py) makes either with ``encode_tensor``,
``Weights.to_float32`` reads any with ``decode_tensor``. A known encoding whose tensors are of another
dtype does not decode; an unknown one (a newer sender's) does, and ``to_float32`` refuses it (kind
"weights_encoding") for the reader to count.
"""

from __future__ import annotations

import numpy as np

from common.wire.errors import WireError

# encoding -> the dtype its tensors travel in; float32 messages keep any of the codecs' DTYPES, as before encodings
WEIGHTS_ENCODINGS = {"float32": None, "float16": "float16", "bfloat16": "uint16"}
FLOAT16_MAX = float(np.finfo(np.float16).max)


def encode_tensor(array: np.ndarray, encoding: str, name: str) -> np.ndarray:
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


def decode_tensor(array: np.ndarray, encoding: str) -> np.ndarray:
    if encoding == "float16":
        return array.astype(np.float32)
    return (array.astype(np.uint32) << np.uint32(16)).view(np.float32)
