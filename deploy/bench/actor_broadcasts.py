"""An actor's env steps/s while weights broadcasts arrive, on 1 torch thread and on torch's default, side by side.

One actor of one simulator (the paper's network, acting with weights and a started strategy, as
actor_speed.py builds it) runs its loop, ``Actor.step``, for a window of each case, the cases taking turns
within each round so that the machine's noise hits all alike:

* torch threads: 1 (what ``run_actor`` sets) or torch's default (this machine's cores);
* broadcasts: none, or the paper network's weights at ``--per-s`` (1.2/s: a learner at 60 updates/s with
  learner.weights_every 50) in float32 or bfloat16. A feeder thread does what the actor's Zenoh thread
  does with each broadcast (decode the message, widen and check it in ``Mailbox.offer_weights``), and the
  actor's loop loads it (``Actor.apply_mail``), as in a run. The bytes' transfer over a socket is left out
  (transport_weights.py measures it).

First the cost of one broadcast by parts, then the table: env steps/s of wall time (median of the rounds,
lowest and highest), and the process's CPU seconds per 1,000 env steps (the feeder thread's included).

    .venv/bin/python deploy/bench/actor_broadcasts.py [--rounds 3] [--seconds 8] [--per-s 1.2]
"""

from __future__ import annotations

import argparse
import os
import statistics
import threading
import time

import torch

from actor.acting import Actor
from actor_speed import acting_actor  # deploy/bench is this script's directory
from common.config import Config
from common.cpu_capability import describe_cpu
from common.network import weights_to_numpy
from common.wire.envelope import decode, encode
from common.wire.messages import Weights

ENCODINGS = ("float32", "bfloat16")
REPEATS = 5


class Feeder:
    """A thread that hands the actor's mailbox one decoded broadcast every 1/per_s seconds, as Zenoh's would."""

    def __init__(self, actor: Actor, data: bytes, per_s: float) -> None:
        self.actor, self.data, self.period_s = actor, data, 1.0 / per_s
        self.stop = threading.Event()
        self.sent = 0
        self.thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self.stop.wait(self.period_s):
            self.actor.mailbox.offer_weights(decode(self.data, Weights))
            self.sent += 1

    def __enter__(self) -> Feeder:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        self.thread.join()


def window(actor: Actor, seconds: float) -> tuple[float, float]:
    """(env steps/s of wall time, CPU seconds per 1,000 env steps) of the actor's loop for `seconds`."""
    steps, wall, cpu = 0, time.perf_counter(), time.process_time()
    while time.perf_counter() - wall < seconds:
        actor.step()
        steps += len(actor.slots)
    return steps / (time.perf_counter() - wall), 1e3 * (time.process_time() - cpu) / steps


def broadcast_costs(actor: Actor, messages: dict[str, bytes]) -> None:
    """Prints the milliseconds of one broadcast's parts: decode, widen and check (Zenoh's thread), load (the loop)."""
    print(f"\n{'encoding':9s} {'MB':>6s} {'decode ms':>10s} {'widen + check ms':>17s} {'load ms':>8s}")
    for encoding, data in messages.items():
        decode_ms, offer_ms, load_ms = [], [], []
        for _ in range(REPEATS):
            start = time.perf_counter()
            message = decode(data, Weights)
            decoded = time.perf_counter()
            actor.mailbox.offer_weights(message)
            offered = time.perf_counter()
            actor.apply_mail()
            decode_ms.append(1e3 * (decoded - start))
            offer_ms.append(1e3 * (offered - decoded))
            load_ms.append(1e3 * (time.perf_counter() - offered))
        print(f"{encoding:9s} {len(data) / 1e6:6.1f} {statistics.median(decode_ms):10.0f} "
              f"{statistics.median(offer_ms):17.0f} {statistics.median(load_ms):8.0f}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=8.0, help="time per case and round")
    parser.add_argument("--per-s", type=float, default=1.2, help="broadcasts a second")
    args = parser.parse_args()
    default_threads = torch.get_num_threads()
    print(f"CPU: {describe_cpu()}; torch's default {default_threads} threads on {os.cpu_count()} cores; "
          f"load average {os.getloadavg()[0]:.2f}", flush=True)
    actor = acting_actor(Config(), envs=1)
    tensors = weights_to_numpy(actor.network)
    messages = {encoding: encode(Weights.from_float32(1, tensors, encoding)) for encoding in ENCODINGS}
    broadcast_costs(actor, messages)
    cases = [(threads, encoding) for threads in (1, default_threads) for encoding in (None, *ENCODINGS)]
    measured: dict[tuple, list[tuple[float, float]]] = {case: [] for case in cases}
    for round_number in range(args.rounds):
        for threads, encoding in cases:
            torch.set_num_threads(threads)
            if encoding is None:
                measured[(threads, encoding)].append(window(actor, args.seconds))
                continue
            with Feeder(actor, messages[encoding], args.per_s):
                measured[(threads, encoding)].append(window(actor, args.seconds))
        print(f"round {round_number + 1}/{args.rounds} done, load average {os.getloadavg()[0]:.2f}", flush=True)
    base = statistics.median(rate for rate, _ in measured[(1, None)])
    print(f"\n| torch threads | broadcasts | env steps/s (lowest-highest) | vs 1 thread, none | CPU s per 1,000 steps |")
    print("|---:|---|---:|---:|---:|")
    for (threads, encoding), rows in measured.items():
        rates = [rate for rate, _ in rows]
        said = "none" if encoding is None else f"{args.per_s:g}/s {encoding}"
        print(f"| {threads} | {said} | {statistics.median(rates):,.0f} ({min(rates):,.0f}-{max(rates):,.0f}) "
              f"| {statistics.median(rates) / base:.2f} | {statistics.median(cpu for _, cpu in rows):.2f} |")
    print(f"\nmedians of {args.rounds} rounds of {args.seconds:g} s; load average at the end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
