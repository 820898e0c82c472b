"""What the replay's snapshot costs: time and bytes per 1,000 episodes, and the longest pause it causes.

Frames are real: the simulator's front camera on a random drive, compressed as the actors do, then
reused to build episodes of --steps steps (the snapshot writes what is stored, so the bytes are those of
real episodes). Measured on a ReplayService as the replay runs it, in a temporary directory:

1. inserting --episodes episodes (each checked: every frame decompressed);
2. the first snapshot of that store (every episode new), a snapshot after 10% new episodes, one with
   nothing new (the manifest only), and restoring the snapshot;
3. the longest pause: inserts run flat out and trace-batch samples at --sample-rate on two threads for
   --seconds, once without snapshots and once with a snapshot every 0.5 s: how long an insert or a
   sample waited for the replay's lock, how long a whole insert took, and the snapshot's own longest
   hold of the lock.

    .venv/bin/python deploy/bench/replay_snapshot.py [--episodes 1000] [--steps 200] [--seconds 10]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from actor.sim import make_env
from common.config_values import load_config
from common.cpu_capability import describe_cpu
from common.wire.frames import FrameStack
from common.wire.messages import Episode
from common.wire.run_shape import check_episode
from replay.service import ReplayService


def real_blobs(config, count: int, seed: int = 0) -> tuple[list[bytes], tuple[int, ...]]:
    env = make_env(config.env, seed=seed)
    rng = np.random.default_rng(seed)
    observation, _ = env.reset(options={"start_set": "train"})
    frames = [observation]
    while len(frames) < count:
        observation, _, terminated, truncated, _ = env.step(int(rng.integers(config.network.n_actions)))
        frames.append(observation)
        if terminated or truncated:
            observation, _ = env.reset(options={"start_set": "train"})
            frames.append(observation)
    stack = FrameStack.from_array(np.stack(frames[:count]))
    return stack.blobs, stack.frame_shape


class Episodes:
    """Episodes of `steps` steps cut from a pool of real compressed frames, each with a new index."""

    def __init__(self, blobs: list[bytes], shape, steps: int, seed: int = 1) -> None:
        self.blobs, self.shape, self.steps = blobs, shape, steps
        self.rng = np.random.default_rng(seed)
        self.index = 0

    def next(self) -> Episode:
        start = int(self.rng.integers(0, len(self.blobs) - self.steps - 1))
        steps = self.steps
        episode = Episode(observations=FrameStack(self.blobs[start:start + steps + 1], self.shape),
                          actions=self.rng.integers(0, 5, steps), rewards=self.rng.random(steps, np.float32),
                          terminated=True, truncated=False, actor_id=0, start_set="train", start_index=0,
                          weights_version=np.zeros(steps, np.int64), epsilon=1.0, seed=0,
                          episode_index=self.index, incarnation=12345)
        self.index += 1
        return episode


def timed(function):
    started = time.perf_counter()
    result = function()
    return result, time.perf_counter() - started


def under_load(service: ReplayService, episodes: Episodes, seconds: float, sample_speed: float,
               snapshot_every: float | None) -> dict:
    """Inserts flat out and samples at sample_speed (and snapshots, if asked): how long each waited for
    the replay's lock, and how long an insert took in all (its frames are checked outside the lock)."""
    stop = threading.Event()
    waits: dict[str, list[float]] = {"insert": [], "sample": [], "insert_total": []}
    counts = {"snapshots": 0}

    def inserts():
        while not stop.is_set():
            episode = episodes.next()
            started = time.perf_counter()
            check_episode(episode, service.shape)  # as on_episode does, outside the lock
            asked = time.perf_counter()
            with service._lock:
                waits["insert"].append(time.perf_counter() - asked)
                if service.ledger.admit(episode.actor_id, episode.incarnation, episode.episode_index):
                    service._store_locked(episode)
            waits["insert_total"].append(time.perf_counter() - started)

    def samples():
        while not stop.wait(1.0 / sample_speed):
            asked = time.perf_counter()
            with service._lock:  # as a reply thread does
                waits["sample"].append(time.perf_counter() - asked)
                service.store.sample(10)

    def snapshots():
        while not stop.wait(snapshot_every):
            service.write_snapshot()
            counts["snapshots"] += 1

    threads = [threading.Thread(target=inserts), threading.Thread(target=samples)]
    if snapshot_every:
        threads.append(threading.Thread(target=snapshots))
    for thread in threads:
        thread.start()
    time.sleep(seconds)
    stop.set()
    for thread in threads:
        thread.join()
    return {**counts, **{name: len(values) for name, values in waits.items()},
            **{f"slowest_{name}_ms": max(values) * 1000 for name, values in waits.items()},
            **{f"p99_{name}_ms": float(np.percentile(values, 99)) * 1000 for name, values in waits.items()}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--sample-rate", type=float, default=100.0,
                        help="trace batches per second under load (the paper's learner takes about 7)")
    args = parser.parse_args()
    print(f"CPU: {describe_cpu()}", flush=True)
    directory = Path(tempfile.mkdtemp(prefix="snapshot-bench-"))
    try:
        config = load_config("paper", overrides={"replay.capacity": args.episodes, "run.runs_dir": str(directory),
                                                 "run.name": "bench", "env.max_steps": max(2000, args.steps)})
        blobs, shape = real_blobs(config, 4 * args.steps + 2)
        print(f"{len(blobs)} real frames of {list(shape)}: {np.mean([len(b) for b in blobs]):.0f} bytes each "
              f"compressed; episodes of {args.steps} steps")
        episodes = Episodes(blobs, shape, args.steps)
        service = ReplayService(config)
        _, took = timed(lambda: [service.on_episode(episodes.next()) for _ in range(args.episodes)])
        print(f"insert (every frame checked): {took / args.episodes * 1000:.2f} ms per episode")
        rows = []
        for label, new in (("first snapshot, every episode new", 0),  # the store was just filled
                           ("after 10% new episodes", args.episodes // 10), ("nothing new (manifest only)", 0)):
            for _ in range(new):
                service.on_episode(episodes.next())
            service.write_snapshot()
            stats = service.stats()
            rows.append((label, stats["snapshot_written_episodes"], stats["snapshot_written_bytes"],
                         stats["snapshot_seconds"], stats["snapshot_pause_ms"]))
        print(f"\n{'snapshot':40s} {'episodes':>8s} {'MB written':>10s} {'seconds':>8s} {'lock ms':>8s}"
              f" {'s per 1,000':>11s} {'MB per 1,000':>12s}")
        for label, count, written, seconds, pause in rows:
            per = 1000 / count if count else 0.0
            print(f"{label:40s} {count:8d} {written / 2**20:10.1f} {seconds:8.3f} {pause:8.2f} "
                  f"{seconds * per:11.3f} {written / 2**20 * per:12.1f}")
        print(f"snapshot on disk: {service.snapshot_stats['snapshot_bytes'] / 2**20:.1f} MB for "
              f"{service.snapshot_stats['snapshot_episodes']} episodes")
        fresh = ReplayService(config)
        restored, took = timed(lambda: fresh.snapshotter.load(shape))
        _, took_restore = timed(lambda: fresh.restore(restored, None))
        print(f"restore: {len(restored.episodes)} episodes read in {took:.2f} s, taken in {took_restore:.3f} s")
        print(f"\nunder load ({args.seconds:g} s, inserts flat out, {args.sample_speed:g} samples/s of 10 traces):")
        for label, every in (("no snapshots", None), ("a snapshot every 0.5 s", 0.5)):
            service.snapshot_stats["snapshot_pause_max_ms"] = 0.0
            result = under_load(service, episodes, args.seconds, args.sample_speed, every)
            held = service.snapshot_stats["snapshot_pause_max_ms"]
            print(f"  {label:24s} lock wait: insert slowest {result['slowest_insert_ms']:6.2f} ms (p99 "
                  f"{result['p99_insert_ms']:5.2f}), sample slowest {result['slowest_sample_ms']:6.2f} ms (p99 "
                  f"{result['p99_sample_ms']:5.2f}); a whole insert: slowest {result['slowest_insert_total_ms']:6.1f} "
                  f"ms (p99 {result['p99_insert_total_ms']:5.1f}); {result['insert']} inserts, {result['sample']} "
                  f"samples, {result['snapshots']} snapshots, longest lock hold by a snapshot {held:.2f} ms")
    finally:
        shutil.rmtree(directory, ignore_errors=True)


if __name__ == "__main__":
    main()
