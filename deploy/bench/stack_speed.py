"""Benchmark: the distributed stack against the reference loop, side by side, and the replay flat out.

1. the reference loop (deploy/reference_loop.py): act, store, sample, update
   and feed the exploration strategy in one process, one update per
   pace.env_steps_per_update env steps, every strategy hook called;
2. the local stack (replay + learner + actors over loopback Zenoh), same config;
3. the replay service queried for trace batches as fast as it answers.

Parts 1 and 2 are measured once updates run at the configured ratio, over
--seconds of wall time: the loop from the start of updates, the stack once the
learner has paid for the steps the actors took before they heard that updates
began. Both fill the buffer with at most 50 episodes first.
Usage: .venv/bin/python deploy/bench/stack_speed.py [--seconds 60] [--actors 1] [config flags]
"""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from tempfile import TemporaryDirectory

import numpy as np
import torch

from actor.acting import Actor
from common.config import Config, TransportConfig
from common.config_cli import add_config_arguments, parse_config_or_exit
from common.config_values import to_toml
from common.cpu_capability import describe_cpu
from common.transport import free_port, loopback_endpoint, open_session, publisher, request, subscribe
from common.keys import Keys
from common.wire.messages import RateState, ReplayStats, TraceBatch, TraceBatchRequest
from deploy.reference_loop import train
from learner.trace_batch import TraceArrays
from learner.update import DoubleQLearner

ROOT = Path(__file__).resolve().parents[2]


def reference_loop(config: Config, seconds: float) -> tuple[float, float]:
    """deploy/reference_loop.py for `seconds` once updates start; returns (env steps/s, updates/s) over them."""
    if config.learner.update_path == "auto":
        time_update_paths(config)
    result = train(config, evaluate_at_end=False, update_seconds=seconds)
    steps = result.env_steps - result.start_env_steps
    return steps / result.seconds_updating, result.updates / result.seconds_updating


def time_update_paths(config: Config) -> None:
    """learner.update_path "auto" times the update paths on the first batch, once per process; do it here, so
    the loop's measured window does not hold it (the stack is measured long after its learner did it)."""
    learner_config, network = config.learner, config.network
    shape = (learner_config.batch_size, learner_config.trace_length + 1, network.frame_height, network.frame_width,
             network.frame_channels)
    steps = shape[:1] + (learner_config.trace_length,)
    DoubleQLearner(network, learner_config).update(TraceArrays(np.zeros(shape, np.uint8), np.zeros(steps, np.int64),
                                                               np.zeros(steps, np.float32), np.zeros(steps, bool)))


def local_stack(config: Config, seconds: float, actors: int) -> tuple[float, float]:
    """Starts deploy/launcher/stack.py; returns (env steps/s, updates/s) over the window after updates start."""
    with TemporaryDirectory() as runs:
        port = free_port()
        flags = ["--config", str(Path(runs) / "bench.toml"), "--run.runs_dir", runs, "--run.name", "bench",
                 "--actors", str(actors), "--port", str(port), "--recorder.enabled", "false"]
        (Path(runs) / "bench.toml").write_text(to_toml(config))
        stack = subprocess.Popen([sys.executable, str(ROOT / "deploy" / "launcher" / "stack.py"), *flags],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        session = open_session(TransportConfig(mode="client", connect=[loopback_endpoint(port)]))
        seen: dict[str, ReplayStats] = {}  # the replay's latest stats
        keys = Keys(config.transport.namespace, "bench")
        subscription = subscribe(session, keys.replay_stats, lambda message, key: seen.update(last=message),
                                 expected=ReplayStats)
        try:
            # Steps the actors took at random-play speed before they heard that updates began are
            # owed updates; measure once the learner has paid them (within the rate limiter's buffer).
            while "last" not in seen or not caught_up(seen["last"].rate):
                time.sleep(0.2)
            first = (time.monotonic(), seen["last"].env_steps_total, seen["last"].rate.batches_served)
            time.sleep(seconds)
            last = (time.monotonic(), seen["last"].env_steps_total, seen["last"].rate.batches_served)
        finally:
            subscription.undeclare()
            session.close()
            stack.send_signal(signal.SIGINT)
            stack.wait(120)
    elapsed = last[0] - first[0]
    return (last[1] - first[1]) / elapsed, (last[2] - first[2]) / elapsed


def caught_up(rate: RateState) -> bool:
    """Updates have started and the learner is within the actors' lead of what is due (the lag a learner
    slower than its actors keeps)."""
    if not rate.updates_started or rate.batches_served < 1:
        return False
    return rate.updates_due - rate.batches_served <= rate.hold_updates


def replay_flat_out(config: Config, seconds: float, clients: int) -> tuple[float, float]:
    """Fills a replay process with real episodes and queries it from `clients` threads."""
    endpoint = loopback_endpoint()
    # The rate limiter let loose: updates start at the first episode, and 1e9 updates of error buffer never hold.
    replay = subprocess.Popen([sys.executable, "-m", "replay.main", "--run.name", "flat", "--transport.mode", "router",
                               "--transport.listen", endpoint, "--pace.start_episodes", "1",
                               "--pace.error_buffer_updates", "1e9"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    session = open_session(TransportConfig(mode="client", connect=[endpoint]))
    keys = Keys(config.transport.namespace, "flat")
    try:
        episodes = publisher(session, keys.episodes)
        while not episodes.matched:
            time.sleep(0.05)
        actor, stop = Actor(config, actor_id=0), threading.Event()
        for _ in range(200):
            episodes.put(actor.run_episode(stop)[0])
        served = [0] * clients
        nbytes = [0] * clients
        deadline = time.monotonic() + seconds

        def client(index: int) -> None:
            while time.monotonic() < deadline:
                batch = request(session, keys.replay_sample, TraceBatchRequest(
                    request_id=index, batch_size=config.learner.batch_size,
                    trace_length=config.learner.trace_length), 10.0, expected=TraceBatch)
                if batch is not None:
                    served[index] += batch.batch_size
                    nbytes[index] += batch.observations.nbytes

        threads = [threading.Thread(target=client, args=(n,)) for n in range(clients)]
        started = time.monotonic()
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        elapsed = time.monotonic() - started
    finally:
        session.close()
        replay.send_signal(signal.SIGINT)
        replay.wait(30)
    return sum(served) / elapsed, sum(nbytes) / elapsed / 1e6


def main() -> None:
    parser = argparse.ArgumentParser(prog="stack_speed", description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="measuring window of each part")
    parser.add_argument("--actors", type=int, default=1)
    parser.add_argument("--clients", type=int, default=2, help="parallel query threads for the replay part")
    add_config_arguments(parser)
    args, config = parse_config_or_exit(parser)
    print(f"CPU: {describe_cpu()}", flush=True)
    config.pace.start_episodes = min(config.pace.start_episodes, 50)  # both sides: a short fill
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; B={config.learner.batch_size} "
          f"T={config.learner.trace_length}, LSTM {config.network.lstm_units}, "
          f"{config.pace.env_steps_per_update:g} env steps per update; {args.seconds:.0f} s windows", flush=True)
    print("1/3 reference loop (one process) ...", flush=True)
    loop = reference_loop(config, args.seconds)
    print(f"2/3 local stack with {args.actors} actor(s) ...", flush=True)
    stack = local_stack(config, args.seconds, args.actors)
    print(f"    {'':28} {'env steps/s':>12} {'updates/s':>10} {'steps/update':>13}")
    for name, (steps, updates) in (("reference loop", loop), (f"local stack, {args.actors} actor(s)", stack)):
        print(f"    {name:28} {steps:12.1f} {updates:10.2f} {steps / updates:13.2f}")
    print(f"    {'stack / reference loop':28} {stack[0] / loop[0]:11.2f}x {stack[1] / loop[1]:9.2f}x", flush=True)
    if abs(stack[0] / stack[1] / config.pace.env_steps_per_update - 1) > 0.1:
        print(f"    (the stack's window is short against the rate limiter's error buffer of "
              f"{config.pace.error_buffer_updates:g} updates, so its steps per update are off the configured "
              f"{config.pace.env_steps_per_update:g}: compare updates/s, or lengthen --seconds)", flush=True)
    print(f"3/3 replay flat out, {args.clients} client threads ...", flush=True)
    traces, megabytes = replay_flat_out(config, min(args.seconds, 20.0), args.clients)
    print(f"    traces served/s {traces:8.1f}   ({megabytes:.1f} MB/s of compressed frames)")


if __name__ == "__main__":
    main()
