"""Weights messages at the paper's sizes (~48.6 MB of float32): encodings, shared memory, subscribers.

In one run, side by side:
  * encode and decode (with the finite check, then widened to float32 as an actor does) per encoding;
  * a broadcast to 1, 2 and 4 subscribers, each its own process on this host, per encoding, with
    Zenoh shared memory on and off (transport.shared_memory): the latency from the learner's
    weights to the last subscriber holding them decoded as float32, and what that makes per
    actor: MB/s of the message, and broadcasts/s;
  * the latest-weights query (an actor's ask at start) per encoding, between two sessions of this
    process.
Peer sessions on tcp/127.0.0.1, multicast off. Every process shares the machine's cores: under
load the figures are only good side by side, so the load average is printed with them.

    .venv/bin/python deploy/bench/transport_weights.py [--repeats 5] [--subscribers 1 2 4]
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import statistics
import time

import numpy as np

from common.cpu_capability import describe_cpu
from common.config import NetworkConfig, TransportConfig
from common.transport import loopback_endpoint, open_session, publisher, request, serve, subscribe
from common.shared_memory import SharedMemory
from common.keys import Keys
from common.wire.envelope import decode, encode
from common.wire.messages import Weights
from common.wire.weights_encoding import WEIGHTS_ENCODINGS
from wire_sizes import d3rqn_tensors

TIMEOUT_S = 60.0
KEYS = Keys("d3rqn-bench", "weights")
MB = 1e6


def wait_until(predicate, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise SystemExit("timed out waiting for Zenoh discovery")
        time.sleep(0.01)


def timed(function) -> float:
    start = time.perf_counter()
    if function() is None:
        raise SystemExit("a transfer failed")
    return time.perf_counter() - start


def subscriber(endpoint: str, shared_memory: bool, ready, arrivals, stop) -> None:
    """A spawned actor stand-in: each broadcast decoded and widened to float32; reports (version, when, in shm)."""
    def on_weights(message: Weights, key: str) -> None:
        message.to_float32()
        arrivals.put((message.version, time.monotonic(), receiver.shared))

    config = TransportConfig(connect=[endpoint], shared_memory=shared_memory)
    with open_session(config) as session, subscribe(session, KEYS.weights, on_weights, expected=Weights) as receiver:
        ready.put(os.getpid())
        stop.wait(TIMEOUT_S * 10)


def broadcasts(tensors: dict[str, np.ndarray], shared_memory: bool, subscribers: int, repeats: int) -> dict:
    """{encoding: (median latency s, message bytes, whether every subscriber got it in shared memory)}."""
    context = multiprocessing.get_context("spawn")
    ready, arrivals, stop = context.Queue(), context.Queue(), context.Event()
    endpoint = loopback_endpoint()
    config = TransportConfig(listen=[endpoint], shared_memory=shared_memory)
    results = {}
    with open_session(config) as session, \
            publisher(session, KEYS.weights, shared_memory=SharedMemory.of(config)) as out:
        children = [context.Process(target=subscriber, args=(endpoint, shared_memory, ready, arrivals, stop))
                    for _ in range(subscribers)]
        for child in children:
            child.start()
        try:
            for _ in children:
                ready.get(timeout=TIMEOUT_S)
            wait_until(lambda: out.matched)
            version = 0
            for encoding in WEIGHTS_ENCODINGS:
                latencies, size, shared = [], 0, []
                for repeat in range(repeats + 1):  # the first warms up: fresh shared memory pages fault in
                    version += 1
                    start = time.monotonic()
                    size = out.put(Weights.from_float32(version, tensors, encoding, created=time.time()))
                    done = [arrivals.get(timeout=TIMEOUT_S) for _ in children]
                    if any(got != version for got, _, _ in done):
                        raise SystemExit("a subscriber missed a broadcast")
                    if repeat:
                        latencies.append(max(when for _, when, _ in done) - start)
                        # every broadcast so far came in shared memory: as many such samples as versions
                        shared.append(all(count == version for _, _, count in done))
                results[encoding] = (statistics.median(latencies), size, all(shared))
        finally:
            stop.set()
            for child in children:
                child.join(TIMEOUT_S)
                if child.is_alive():
                    child.kill()
    return results


def queries(tensors: dict[str, np.ndarray], repeats: int) -> dict[str, float]:
    """{encoding: median seconds of a latest-weights query, decoded and widened}."""
    endpoint = loopback_endpoint()
    results = {}
    with open_session(TransportConfig(listen=[endpoint])) as learner, \
            open_session(TransportConfig(connect=[endpoint])) as actor:
        for encoding in WEIGHTS_ENCODINGS:
            weights = Weights.from_float32(1, tensors, encoding)
            with serve(learner, KEYS.weights_latest, lambda message: weights):
                wait_until(lambda: request(actor, KEYS.weights_latest, None, TIMEOUT_S) is not None)
                results[encoding] = statistics.median(
                    timed(lambda: request(actor, KEYS.weights_latest, None, TIMEOUT_S, expected=Weights).to_float32())
                    for _ in range(repeats))
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--subscribers", type=int, nargs="+", default=[1, 2, 4])
    args = parser.parse_args()
    print(f"CPU: {describe_cpu()}", flush=True)
    tensors = d3rqn_tensors(NetworkConfig(), np.random.default_rng(0))
    print(f"{sum(t.size for t in tensors.values()):,} float32 parameters; load average at start "
          f"{os.getloadavg()[0]:.2f} on {os.cpu_count()} cores; medians of {args.repeats}")

    print(f"\n{'encoding':9s} {'message MB':>10s} {'encode ms':>10s} {'decode + widen ms':>18s}")
    for encoding in WEIGHTS_ENCODINGS:
        encode_s = statistics.median(timed(lambda: encode(Weights.from_float32(1, tensors, encoding)))
                                     for _ in range(args.repeats))
        data = encode(Weights.from_float32(1, tensors, encoding))
        decode_s = statistics.median(timed(lambda: decode(data, Weights).to_float32()) for _ in range(args.repeats))
        print(f"{encoding:9s} {len(data) / MB:10.1f} {encode_s * 1e3:10.0f} {decode_s * 1e3:18.0f}")

    print(f"\nbroadcast: learner's weights -> every subscriber holds them as float32 (latency of the last)")
    print(f"{'subscribers':>11s} {'shm':>4s} {'encoding':9s} {'latency ms':>10s} {'MB/s per actor':>15s} "
          f"{'broadcasts/s':>13s} {'via shm':>8s}")
    for count in args.subscribers:
        for shared_memory in (True, False):
            for encoding, (latency, size, shared) in broadcasts(tensors, shared_memory, count, args.repeats).items():
                print(f"{count:11d} {'on' if shared_memory else 'off':>4s} {encoding:9s} {latency * 1e3:10.0f} "
                      f"{size / MB / latency:15.0f} {1 / latency:13.1f} {'yes' if shared else 'no':>8s}")

    print("\nlatest-weights query -> decoded and widened reply (two sessions of this process)")
    for encoding, seconds in queries(tensors, args.repeats).items():
        print(f"  {encoding:9s} {seconds * 1e3:7.0f} ms")
    print(f"\nload average at the end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
