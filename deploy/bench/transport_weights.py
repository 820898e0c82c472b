"""Time to pass a D3RQN-sized Weights message (~48.6 MB) between two Zenoh sessions on loopback.

Both sessions live in this process (peer mode, tcp/127.0.0.1, multicast off), so the
figures include encode, transfer and decode but share the machine's cores with both ends.

    .venv/bin/python deploy/bench/transport_weights.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import queue
import statistics
import time

import numpy as np

from common.config import NetworkConfig, TransportConfig
from common.transport import Keys, loopback_endpoint, open_session, publisher, request, serve, subscribe
from common.wire import Weights, decode, encode
from wire_sizes import d3rqn_tensors

TIMEOUT_S = 30.0


def wait_until(predicate, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise SystemExit("timed out waiting for Zenoh discovery")
        time.sleep(0.01)


def summary(name: str, seconds: list[float], size: int) -> str:
    best, median = min(seconds), statistics.median(seconds)
    return f"  {name:34s} median {median * 1e3:7.1f} ms  best {best * 1e3:7.1f} ms  ({size / median / 1e6:6.0f} MB/s)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    weights = Weights(version=1, tensors=d3rqn_tensors(NetworkConfig(), np.random.default_rng(0)), created=time.time())
    size = len(encode(weights))
    print(f"Weights message: {size:,} bytes, {sum(t.size for t in weights.tensors.values()):,} float32 parameters")

    encode_s = [timed(lambda: encode(weights)) for _ in range(args.repeats)]
    data = encode(weights)
    decode_s = [timed(lambda: decode(data, Weights)) for _ in range(args.repeats)]

    endpoint = loopback_endpoint()
    keys = Keys("d3rqn-bench", "weights")
    with open_session(TransportConfig(listen=[endpoint])) as learner, \
            open_session(TransportConfig(connect=[endpoint])) as actor:
        inbox: queue.Queue = queue.Queue()
        with subscribe(actor, keys.weights, lambda message, key: inbox.put(time.perf_counter()), expected=Weights), \
                publisher(learner, keys.weights) as out, \
                serve(learner, keys.weights_latest, lambda message: weights):
            wait_until(lambda: out.matched)
            wait_until(lambda: request(actor, keys.weights_latest, None, TIMEOUT_S) is not None)
            publish_s = []
            for _ in range(args.repeats):
                start = time.perf_counter()
                out.put(weights)
                publish_s.append(inbox.get(timeout=TIMEOUT_S) - start)
            query_s = [timed(lambda: request(actor, keys.weights_latest, None, TIMEOUT_S, expected=Weights))
                       for _ in range(args.repeats)]

    print(f"{args.repeats} runs each:")
    print(summary("encode", encode_s, size))
    print(summary("decode (with finite check)", decode_s, size))
    print(summary("publish -> decoded in subscriber", publish_s, size))
    print(summary("request -> decoded reply", query_s, size))


def timed(function) -> float:
    start = time.perf_counter()
    if function() is None:
        raise SystemExit("a transfer failed")
    return time.perf_counter() - start


if __name__ == "__main__":
    main()
