"""The two ends of a weights broadcast, each run in a spawned process by tests/test_weights_broadcasts.py
(a Zenoh session lives only in a fresh interpreter); light imports, so they start fast."""

from __future__ import annotations

import time

import numpy as np

from common.config import TransportConfig
from common.transport import open_session, publisher, subscribe
from common.shared_memory import SharedMemory
from common.keys import Keys
from common.wire.messages import Weights

KEYS = Keys("d3rqn-test", "shm")
RECEIVE_TIMEOUT_S = 20.0


def example_tensors() -> dict[str, np.ndarray]:
    """4 MB of float32: large enough that Zenoh fragments it on a socket."""
    return {"w": np.random.default_rng(0).normal(size=1_000_000).astype(np.float32)}


def publish_weights(endpoint: str, shared_memory: bool, stop, report) -> None:
    """Puts the example weights twice a second until stopped; reports its pool's (shared, fallbacks)."""
    config = TransportConfig(listen=[endpoint], shared_memory=shared_memory)
    pool = SharedMemory.of(config)
    tensors = example_tensors()
    with open_session(config) as session, publisher(session, KEYS.weights, shared_memory=pool) as out:
        version = 0
        while not stop.wait(0.5):
            out.put(Weights.from_float32(version, tensors))
            version += 1
    report.put(("publisher", None if pool is None else (pool.shared, pool.fallbacks)))


def receive_weights(endpoint: str, shared_memory: bool, report) -> None:
    """Reports the first weights that arrive (version, one value) and how many samples came in shared memory."""
    config = TransportConfig(connect=[endpoint], shared_memory=shared_memory)
    inbox: list[Weights] = []
    with open_session(config) as session, \
            subscribe(session, KEYS.weights, lambda message, key: inbox.append(message), expected=Weights) as received:
        deadline = time.monotonic() + RECEIVE_TIMEOUT_S
        while not inbox and time.monotonic() < deadline:
            time.sleep(0.05)
        first = inbox[0] if inbox else None
        report.put(("subscriber", None if first is None else
                    (first.version, float(first.to_float32()["w"][7]), received.shared)))
