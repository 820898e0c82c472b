"""actor.weights_download: the learner's weights in pieces (learner/weights_shelf.py), downloaded one
piece at a time (actor/weights_download.py), through the wire both ways as over Zenoh."""

import math
import time
import threading

import numpy as np
import pytest

from actor.weights_download import download_weights
from common.config_values import load_config
from common.wire.envelope import decode, encode
from common.wire.errors import WireError
from common.wire.messages import Weights, WeightsPiece, WeightsPieceAsk
from learner.service import LearnerService
from learner.weights_shelf import WeightsShelf

PIECE = 1000


def weights(version: int, seed: int = 0) -> Weights:
    rng = np.random.default_rng(seed)
    return Weights.from_float32(version, {"a": rng.normal(size=(40, 30)).astype(np.float32),
                                          "b": rng.normal(size=77).astype(np.float32)})


class Wire:
    """Asks the shelf as an actor asks the learner: each message encoded and decoded on the way."""

    def __init__(self, shelf: WeightsShelf, between=lambda asked: None) -> None:
        self.shelf, self.between, self.asked = shelf, between, 0

    def __call__(self, ask: WeightsPieceAsk) -> WeightsPiece | None:
        self.asked += 1
        self.between(self.asked)
        piece = self.shelf.piece(decode(encode(ask), WeightsPieceAsk))
        return None if piece is None else decode(encode(piece), WeightsPiece)


def same(got: Weights, sent: Weights) -> bool:
    return got.version == sent.version and all(np.array_equal(got.tensors[name], sent.tensors[name])
                                               for name in sent.tensors)


def test_a_download_reassembles_the_latest_weights_piece_by_piece():
    sent = weights(7)
    wire = Wire(WeightsShelf(lambda: sent))
    got = download_weights(wire, threading.Event(), piece_bytes=PIECE)
    assert same(got, sent)
    assert wire.asked == math.ceil(len(encode(sent)) / PIECE) > 5  # one ask a piece, no more


def test_a_download_finishes_on_its_version_while_the_learner_moves_on():
    latest = [weights(1, seed=1)]
    shelf = WeightsShelf(lambda: latest[0])

    def move_on(asked: int) -> None:  # mid-download, the learner broadcasts v2 and another actor begins on it
        if asked == 3:
            latest[0] = weights(2, seed=2)
            shelf.piece(WeightsPieceAsk(version=-1, offset=0, size=PIECE))

    wire = Wire(shelf, between=move_on)
    assert same(download_weights(wire, threading.Event(), piece_bytes=PIECE), weights(1, seed=1))  # kept for it
    assert same(download_weights(wire, threading.Event(), piece_bytes=PIECE), weights(2, seed=2))


def test_a_version_the_shelf_let_go_starts_the_download_again_on_the_latest():
    latest = [weights(1, seed=1)]
    shelf = WeightsShelf(lambda: latest[0], kept=1)

    def move_on(asked: int) -> None:  # the other actor's download pushes v1 off a shelf that keeps one
        if asked == 3:
            latest[0] = weights(2, seed=2)
            shelf.piece(WeightsPieceAsk(version=-1, offset=0, size=PIECE))

    wire = Wire(shelf, between=move_on)
    got = download_weights(wire, threading.Event(), piece_bytes=PIECE)
    assert same(got, weights(2, seed=2))
    assert wire.asked == 2 + 1 + math.ceil(len(encode(latest[0])) / PIECE)  # v1's two, v2's piece 2 refused, v2's


def test_no_weights_yet_or_a_stop_gives_nothing():
    assert download_weights(Wire(WeightsShelf(lambda: None)), threading.Event()) is None
    stopped = threading.Event()
    stopped.set()
    assert download_weights(Wire(WeightsShelf(lambda: weights(1))), stopped) is None


def test_bytes_that_are_no_weights_message_are_refused():
    blob = np.frombuffer(b"not a message at all", dtype=np.uint8)
    piece = WeightsPiece(version=1, total_bytes=len(blob), offset=0, data=blob)
    with pytest.raises(WireError):
        download_weights(lambda ask: piece, threading.Event())


@pytest.mark.parametrize("offset, size, total", [(10, 5, 12), (0, 0, 12), (0, (1 << 20) + 1, (1 << 20) + 1)])
def test_a_piece_outside_its_weights_or_empty_or_too_large_does_not_decode(offset, size, total):
    piece = WeightsPiece(version=1, total_bytes=total, offset=offset, data=np.zeros(size, np.uint8))
    with pytest.raises(WireError):
        decode(encode(piece))


def test_the_learner_serves_pieces_and_refuses_and_counts_other_asks(tmp_path):
    config = load_config("smoke", overrides={"network.lstm_units": 16, "run.runs_dir": str(tmp_path)})
    service = LearnerService(config)
    assert service.serve_weights_piece(WeightsPieceAsk(version=-1, offset=0, size=PIECE)) is None  # none yet
    sent = service.make_weights()
    piece = service.serve_weights_piece(WeightsPieceAsk(version=-1, offset=0, size=PIECE))
    assert (piece.version, piece.offset, len(piece.data), piece.total_bytes) == (sent.version, 0, PIECE,
                                                                               len(encode(sent)))
    assert service.serve_weights_piece(WeightsPieceAsk(version=-1, offset=piece.total_bytes, size=PIECE)) is None
    assert service.serve_weights_piece(None) is None and service.serve_weights_piece(sent) is None
    assert service.rejections.values()["rejected_weights_piece_query"] == 2


def test_a_downloading_actor_is_late_only_after_three_periods_without_a_download(tmp_path):
    from actor.acting import Actor
    from actor.runner import _stale
    config = load_config("smoke", overrides={"network.lstm_units": 16, "actor.weights_download": True,
                                             "actor.weights_download_period_s": 10.0})
    actor = Actor(config, 0)
    actor.weights_download_s = 20.0  # a slow link: the last download took 20 s
    actor.weights_downloaded_at = time.monotonic() - 45.0
    assert not _stale(actor, behind_broadcasts=True)  # 45 s < 3 x 10 + 20: many broadcasts' worth, not late
    actor.weights_downloaded_at = time.monotonic() - 51.0
    assert _stale(actor, behind_broadcasts=False)
    broadcast = Actor(load_config("smoke", overrides={"network.lstm_units": 16}), 0)
    assert _stale(broadcast, True) and not _stale(broadcast, False)


def test_an_answer_claiming_absurd_weights_is_given_up_at_once():
    asked = []

    def hostile(ask):
        asked.append(ask)
        return WeightsPiece(version=1, total_bytes=1 << 40, offset=ask.offset, data=np.zeros(8, np.uint8))

    assert download_weights(hostile, threading.Event()) is None and len(asked) == 1
