"""An actor's download of the learner's latest weights, piece by piece at its link's pace
(actor.weights_download; the learner's side is learner/weights_shelf.py).

Each piece is asked for once the one before has come, so no queue between the learner and this actor
ever holds more than a piece: a slow link slows only this actor's downloads, never the learner. A piece
of another version than the one begun (the learner dropped it from its shelf) starts the download again
on that version; a download that starts again too often is given up (None), and one whose bytes are not
a Weights message raises WireError: both are tried again at the next period.
"""

from __future__ import annotations

import threading
from typing import Callable

from common.wire.envelope import decode
from common.wire.messages import Weights, WeightsPiece, WeightsPieceAsk

PIECE_BYTES = 48 * 1024  # within one Zenoh batch (64 KB), so a piece never waits on a queue behind itself
MAX_RESTARTS = 3
MAX_WEIGHTS_BYTES = 1 << 30  # the paper's network is 48.6 MB as float32


def download_weights(ask: Callable[[WeightsPieceAsk], WeightsPiece | None], stop: threading.Event,
                     piece_bytes: int = PIECE_BYTES) -> Weights | None:
    """The learner's latest weights, or None (no answer, stopped, or given up)."""
    version, pieces, offset, restarts, total = -1, [], 0, -1, -1
    while not stop.is_set():
        piece = ask(WeightsPieceAsk(version=version, offset=offset, size=piece_bytes))
        if piece is None:
            return None
        if piece.total_bytes > MAX_WEIGHTS_BYTES:  # no network of this project is near it: a hostile answer
            return None
        if piece.version != version or piece.offset != offset or piece.total_bytes != total:  # first, or another
            total = piece.total_bytes
            restarts += 1
            if restarts > MAX_RESTARTS:
                return None
            version, pieces, offset = piece.version, [], 0
            if piece.offset != 0:
                continue
        pieces.append(piece.data.tobytes())
        offset += len(piece.data)
        if offset >= piece.total_bytes:
            return decode(b"".join(pieces), Weights)
    return None
