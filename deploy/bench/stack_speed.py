"""Benchmark: the distributed stack against a single-process loop, and the replay flat out.

1. single process, as the paper's code runs: act, store, one update per 4 steps
   (here done at the end of each episode: the same work, in bigger bursts);
2. the local stack (replay + learner + actors over loopback Zenoh), same preset;
3. the replay service queried for trace batches as fast as it answers.

Each figure is measured after updates start, over --seconds of wall time.
Usage: .venv/bin/python deploy/bench/stack_speed.py [--seconds 60] [config flags]
"""

from __future__ import annotations

import argparse
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from tempfile import TemporaryDirectory

import numpy as np
import torch

from actor.runner import Actor
from common.config import Config, TransportConfig, add_config_arguments, parse_config_or_exit, to_toml
from common.transport import Keys, open_session, publisher, request, subscribe
from common.wire import Stats, TraceBatch, TraceBatchRequest
from learner.update import DoubleQLearner, TraceBatch as Traces
from replay.store import EpisodeStore

ROOT = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def single_process(config: Config, seconds: float) -> tuple[float, float]:
    """The paper's loop in one process; returns (env steps/s, updates/s) after the fill."""
    actor = Actor(config, actor_id=0)
    learner = DoubleQLearner(config.network, config.learner)
    store = EpisodeStore(config.replay.capacity, 1 << 40, config.learner.trace_length)
    stop = threading.Event()
    while len(store) < config.learner.start_episodes:  # random phase
        store.add(actor.run_episode(stop)[0])
    actor.strategy.start()
    actor.network.load_state_dict(learner.online.state_dict())
    actor.weights_version = 0
    steps = updates = 0
    per_update = config.learner.env_steps_per_update
    started = time.monotonic()
    while time.monotonic() - started < seconds:
        episode, _ = actor.run_episode(stop)  # the updates it pays for follow at its end
        store.add(episode)
        steps += len(episode.actions)
        while updates < steps / per_update and time.monotonic() - started < seconds:
            batch = store.sample(config.learner.batch_size)
            learner.update(Traces(batch.observations_array(), np.array(batch.actions), np.array(batch.rewards),
                                  np.array(batch.terminated)))
            updates += 1
            if updates % config.learner.weights_every == 0:
                actor.network.load_state_dict(learner.online.state_dict())
    elapsed = time.monotonic() - started
    return steps / elapsed, updates / elapsed


def local_stack(config: Config, seconds: float, actors: int) -> tuple[float, float]:
    """Starts deploy/stack.py; returns (env steps/s, updates/s) over the window after updates start."""
    with TemporaryDirectory() as runs:
        port = free_port()
        flags = ["--config", str(Path(runs) / "bench.toml"), "--run.runs_dir", runs, "--run.name", "bench",
                 "--actors", str(actors), "--port", str(port), "--record.enabled", "false"]
        (Path(runs) / "bench.toml").write_text(to_toml(config))
        stack = subprocess.Popen([sys.executable, str(ROOT / "deploy" / "stack.py"), *flags],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        session = open_session(TransportConfig(mode="client", connect=[f"tcp/127.0.0.1:{port}"]))
        seen: dict[str, dict] = {}
        keys = Keys(config.transport.namespace, "bench")
        remember = lambda message, key: seen.__setitem__(key, dict(message.values))
        subscriptions = [subscribe(session, keys.replay_stats, remember, expected=Stats),
                         subscribe(session, keys.learner_progress, remember, expected=Stats)]
        try:
            # Steps the actors took at random-play speed before they heard that updates began are
            # owed updates; measure once the learner has caught up with them.
            while not caught_up(seen.get(keys.learner_progress), config.learner.ratio_tolerance):
                time.sleep(0.2)
            first = (time.monotonic(), seen[keys.replay_stats]["env_steps_total"], seen[keys.learner_progress]["updates"])
            time.sleep(seconds)
            last = (time.monotonic(), seen[keys.replay_stats]["env_steps_total"], seen[keys.learner_progress]["updates"])
        finally:
            for subscription in subscriptions:
                subscription.undeclare()
            session.close()
            stack.send_signal(signal.SIGINT)
            stack.wait(120)
    elapsed = last[0] - first[0]
    return (last[1] - first[1]) / elapsed, (last[2] - first[2]) / elapsed


def caught_up(progress: dict | None, tolerance: float) -> bool:
    return bool(progress) and progress["updates"] >= 1 and progress["updates"] >= progress["updates_due"] * (1 - tolerance)


def replay_flat_out(config: Config, seconds: float, clients: int) -> tuple[float, float]:
    """Fills a replay process with real episodes and queries it from `clients` threads."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    replay = subprocess.Popen([sys.executable, "-m", "replay.main", "--run.name", "flat", "--transport.mode", "router",
                               "--transport.listen", endpoint], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
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
    config.learner.start_episodes = min(config.learner.start_episodes, 50)  # both sides: a short fill
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; B={config.learner.batch_size} "
          f"T={config.learner.trace_length}, LSTM {config.network.lstm_units}, "
          f"{config.learner.env_steps_per_update:g} env steps per update; {args.seconds:.0f} s windows", flush=True)
    print("1/3 single process ...", flush=True)
    single = single_process(config, args.seconds)
    print(f"    env steps/s {single[0]:8.1f}   updates/s {single[1]:6.2f}", flush=True)
    print(f"2/3 local stack with {args.actors} actor(s) ...", flush=True)
    stack = local_stack(config, args.seconds, args.actors)
    print(f"    env steps/s {stack[0]:8.1f}   updates/s {stack[1]:6.2f}", flush=True)
    print(f"    stack / single process: env steps {stack[0] / single[0]:.2f}x, updates {stack[1] / single[1]:.2f}x")
    print(f"3/3 replay flat out, {args.clients} client threads ...", flush=True)
    traces, megabytes = replay_flat_out(config, min(args.seconds, 20.0), args.clients)
    print(f"    traces served/s {traces:8.1f}   ({megabytes:.1f} MB/s of compressed frames)")


if __name__ == "__main__":
    main()
