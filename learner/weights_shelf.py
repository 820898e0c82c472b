"""The learner's weights in pieces, for actors that download them at their link's pace (actor.weights_download).

A broadcast of the paper's network is 24-48 MB. Zenoh forwards it hop by hop with blocking congestion
control, so a slow link to one actor backs the hub's router up into the learner's own link, and the
learner waits with it (docs/reliability.md, a capped link). An actor that downloads instead asks for one
piece at a time and for the next only once it has come: no queue on the way holds more than a piece.

The shelf encodes a version the first time a piece of it is asked for, and keeps the few versions asked
for last, so a slow download finishes on the version it began while the learner moves on.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Callable

import numpy as np

from common.wire.envelope import encode
from common.wire.messages import Weights, WeightsPiece, WeightsPieceAsk

KEPT_VERSIONS = 3  # encoded versions held: the latest and the ones downloads are on


class WeightsShelf:
    def __init__(self, latest: Callable[[], Weights | None], kept: int = KEPT_VERSIONS) -> None:
        self._latest = latest
        self._kept = kept
        self._blobs: OrderedDict[int, bytes] = OrderedDict()  # version -> encoded Weights, least recent first
        self._lock = threading.Lock()

    def piece(self, ask: WeightsPieceAsk) -> WeightsPiece | None:
        """The piece asked for; of the latest version when the one asked for is not held (the asker starts
        again). None before the learner has weights, or for an offset past the end."""
        version, blob = self._blob(ask.version)
        if blob is None or ask.offset >= len(blob):
            return None
        data = np.frombuffer(blob, dtype=np.uint8, count=min(ask.size, len(blob) - ask.offset), offset=ask.offset)
        return WeightsPiece(version=version, total_bytes=len(blob), offset=ask.offset, data=data)

    def _blob(self, version: int) -> tuple[int, bytes | None]:
        with self._lock:
            if version in self._blobs:
                self._blobs.move_to_end(version)
                return version, self._blobs[version]
            latest = self._latest()
            if latest is None:
                return -1, None
            if latest.version not in self._blobs:
                self._blobs[latest.version] = encode(latest)
                while len(self._blobs) > self._kept:
                    self._blobs.popitem(last=False)
            self._blobs.move_to_end(latest.version)
            return latest.version, self._blobs[latest.version]
