"""Image frames as they travel and are stored: a ``FrameStack``, one zstd blob per frame.

The replay keeps episodes compressed and builds trace replies from the stored blobs without
recompressing, and a reader decodes only the frames it needs. ``decode`` (common/wire/envelope.py)
checks each blob's zstd header (declared size = frame size) but does not decompress;
``FrameStack.decode`` and ``FrameStack.verify`` do, and raise WireError for a blob whose content is
corrupt.
"""

from __future__ import annotations

import math
import threading
from typing import Iterable, Sequence

import numpy as np
import zstandard

from common.wire.errors import WireError

ZSTD_LEVEL = 1  # frames are flat-shaded renderings; higher levels buy little and cost time
MAX_FRAME_BYTES = 16 * 2**20  # a declared frame larger than this is refused before decompressing

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
        # a copy: zstandard's blob keeps the allocation of the worst case, the whole frame and more, whatever
        # its length; 1,500 smoke episodes held 1,323 MB where their blobs' lengths summed to 81 MB
        blobs = [bytes(memoryview(compressor.compress(np.ascontiguousarray(frame)))) for frame in frames]
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
