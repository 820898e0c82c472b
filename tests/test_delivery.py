"""Episodes reach the replay once, whatever is lost on the way: the actor's outbox (actor/delivery.py)
sends again what the replay has not said it keeps, and the replay's words (replay/acks.py) say when."""

from __future__ import annotations

import threading
import time

import numpy as np

from actor.delivery import Outbox
from common.wire.envelope import decode, encode
from common.wire.messages import EpisodeAck
from replay.acks import AckBook
from replay.service import ReplayService
from tests.test_hostile_input import SIZE, episode, small_config
from fake_clock import FakeClock

INCARNATION = 7  # tests.test_hostile_input.episode's



def ack(received=(), kept=(), refused=(), actor_id=1, incarnation=INCARNATION) -> EpisodeAck:
    arrays = {name: np.asarray(values, dtype=np.int64) for name, values in
              (("received", received), ("kept", kept), ("refused", refused))}
    return EpisodeAck(actor_id=actor_id, incarnation=incarnation, **arrays)


def outbox(clock: FakeClock, **options) -> Outbox:
    settings = {"resend_after_s": 5.0, "keep_within_s": 60.0, "max_in_flight_bytes": 10**9, **options}
    return Outbox(100, 10**9, incarnation=INCARNATION, actor_id=1, clock=clock, **settings)


def send_due(box: Outbox, sent: list) -> None:
    """What the sender thread does in one round while a replay listens."""
    due = box._next_due()
    if due is not None:
        box._send(sent.append, *due)


def test_a_sent_episode_is_sent_again_until_received_and_held_until_kept():
    clock, sent = FakeClock(100.0), []
    box = outbox(clock)
    box.offer(episode(0), threading.Event())
    send_due(box, sent)
    assert [e.episode_index for e in sent] == [0] and len(box) == 0 and box.in_flight == 1
    clock.now += 4.9
    send_due(box, sent)
    assert len(sent) == 1  # not yet due
    clock.now += 0.2
    send_due(box, sent)
    assert len(sent) == 2 and box.resent == 1  # no word within resend_after_s: lost, sent again
    box.on_ack(ack(received=[0]))
    clock.now += 59.0
    send_due(box, sent)
    assert len(sent) == 2  # received: the replay has it, a snapshot will keep it
    clock.now += 2.0
    send_due(box, sent)
    assert len(sent) == 3  # received, never kept: the word was lost, so again
    box.on_ack(ack(kept=[0]))
    assert box.in_flight == 0 and box.kept == 1
    clock.now += 1000.0
    send_due(box, sent)
    assert len(sent) == 3


def test_a_replay_that_comes_back_gets_every_episode_not_kept_again_first():
    clock, sent = FakeClock(100.0), []
    box = outbox(clock)
    stop = threading.Event()
    for index in range(3):
        box.offer(episode(index), stop)
    for _ in range(3):
        send_due(box, sent)
    box.on_ack(ack(received=[0, 1, 2], kept=[0]))
    box.offer(episode(3), stop)
    box._replay_was_gone = True  # what run() records while no replay listens
    for _ in range(3):
        send_due(box, sent)
    assert [e.episode_index for e in sent] == [0, 1, 2, 1, 2, 3]  # received by the last replay: maybe lost with it


def test_refused_and_foreign_words_and_the_in_flight_bound():
    clock, sent = FakeClock(100.0), []
    size = episode(0).observations.nbytes + episode(0).actions.nbytes * 3
    box = outbox(clock, max_in_flight_bytes=2 * size)
    stop = threading.Event()
    for index in range(3):
        box.offer(episode(index), stop)
        send_due(box, sent)
    assert box.in_flight == 2 and box.released == 1  # the oldest given up past the bound
    box.on_ack(ack(kept=[1], actor_id=2))
    box.on_ack(ack(kept=[1], incarnation=8))  # an earlier incarnation's word
    box.on_ack(episode(5))  # not a word at all
    assert box.in_flight == 2 and box.foreign_acks == 3
    box.on_ack(ack(refused=[1], kept=[2, 99]))  # 99: not in flight, ignored
    values = box.values()
    assert values["episodes_in_flight"] == 0 and values["episodes_refused"] == 1 and values["episodes_kept"] == 1
    assert values["episodes_sent"] == 3 and values["episodes_released"] == 1


def test_the_outbox_holds_episodes_until_a_replay_listens_and_counts_what_it_drops():
    box, listening, sent = Outbox(max_episodes=2, max_bytes=10**9, incarnation=INCARNATION, actor_id=1), \
        threading.Event(), []
    stop, done = threading.Event(), threading.Event()

    def send(episode):
        sent.append(episode)
        box.on_ack(ack(received=[episode.episode_index]))

    sender = threading.Thread(target=box.run, args=(send, listening.is_set, done))
    sender.start()
    try:
        assert box.offer(episode(0), stop) and box.offer(episode(1), stop)
        time.sleep(0.3)
        assert sent == [] and len(box) == 2  # no replay: they wait
        third = threading.Thread(target=box.offer, args=(episode(2), stop))
        third.start()
        time.sleep(0.3)
        assert third.is_alive()  # the outbox is full: the next episode is held
        listening.set()
        third.join(5)
        box.drain(stop)
        assert [e.episode_index for e in sent] == [0, 1, 2] and box.sent == 3
        listening.clear()
        box.offer(episode(3), stop)
    finally:
        done.set()
        sender.join(5)
    assert box.drop_rest() == 1 and box.dropped == 1


def words(book: AckBook) -> dict:
    """{word: sorted indices} over the drained messages, after a trip over the wire."""
    said: dict[str, list[int]] = {}
    for message in book.drain():
        message = decode(encode(message), EpisodeAck)
        for name in ("received", "kept", "refused"):
            said.setdefault(name, []).extend(getattr(message, name).tolist())
    return {name: sorted(indices) for name, indices in said.items() if indices}


def test_the_book_keeps_what_a_snapshot_holds_and_puts_back_what_failed():
    book = AckBook(durable_on_receipt=False)
    book.taken(1, 7, 0)
    book.taken(1, 7, 1)
    book.taken(1, 0, 5)  # unnamed: no word
    assert words(book) == {"received": [0, 1]}
    token = book.view_taken()
    book.taken(1, 7, 2)  # after the view: not in that snapshot
    book.duplicate(1, 7, 1)  # in the view being written: received, not yet kept
    book.view_written(token)
    assert words(book) == {"received": [1, 2], "kept": [0, 1]}
    book.duplicate(1, 7, 0)  # kept before: kept at once
    book.refused(1, 7, 9)
    failed = book.view_taken()
    book.view_failed(failed)
    assert words(book) == {"kept": [0], "refused": [9]}
    book.view_written(book.view_taken())
    assert words(book) == {"kept": [2]}
    on_receipt = AckBook(durable_on_receipt=True)
    on_receipt.taken(3, 4, 0)
    assert words(on_receipt) == {"kept": [0]}


def test_the_replay_says_received_kept_or_refused_for_each_episode(tmp_path):
    service = ReplayService(small_config(tmp_path))
    service.on_episode(episode(0))
    service.on_episode(episode(0))  # sent again: received (no snapshot holds it yet)
    service.on_episode(episode(1, shape=(SIZE + 4, SIZE, 3)))  # not this run's frames
    assert words(service.acks) == {"received": [0, 0], "refused": [1]}
    assert service.write_snapshot()
    assert words(service.acks) == {"kept": [0]}
    service.on_episode(episode(0))
    assert words(service.acks) == {"kept": [0]}
    assert len(service.store) == 1 and service.ledger.duplicates == 2
