"""The learner's prefetcher: how many batches it can take from the replay before an update uses them."""

import threading
import time

import pytest

from common.pacing import learner_stock
from learner.prefetch import Prefetcher


@pytest.mark.parametrize("depth", [1, 2, 3])
def test_a_learner_never_holds_more_batches_than_the_replay_allows_for(depth):
    # The replay owes again what was served beyond learner_stock(prefetch) (replies that never came):
    # a prefetcher that could hold more would be paid twice
    served = []
    lock = threading.Lock()

    def fetch(request):
        with lock:
            served.append(request.request_id)
        return f"batch {request.request_id}"

    prefetcher = Prefetcher(fetch, batch_size=4, trace_length=10, depth=depth)
    stop = threading.Event()
    try:
        assert prefetcher.next(stop, timeout_s=10) is not None  # the batch in the update
        deadline = time.monotonic() + 10
        while len(served) < 2 * depth + 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.3)  # every worker now waits to queue the batch in its hands
        held = len(served)
    finally:
        prefetcher.close()
    assert held == 2 * depth + 1  # queued, one in each worker's hands, one in the update
    assert learner_stock(depth) == held + depth  # and one per worker whose request overtook another's
