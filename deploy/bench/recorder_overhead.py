"""The flight recorder's cost: the stack's env steps/s with and without it, and log bytes per 1,000 env steps.

Runs deploy/launcher/stack.py (smoke preset, --actors 1) in rounds of two runs, recorder on
and off (which goes first alternates), and watches each run over Zenoh. Uniform
random acting while the learner starts is several times faster than acting with
the network and lasts a varying number of steps, so the figure is taken after it: from the first episode the
actor drove with the network (epsilon < 1), over the next --steps environment
steps of the replay's count; then the stack is stopped (SIGINT, as Ctrl-C). The
learner's updates/s over the same span is shown too. Log size per 1,000 env steps
is given for the whole file and without the Weights channel (a few 48 MB weights
per run, whatever its length). Flags after `--` go to the stack.

    .venv/bin/python deploy/bench/recorder_overhead.py [--steps 3000] [--rounds 2] [-- --pace.error_buffer_updates 1e9]
"""

from __future__ import annotations

import argparse
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

from common.config import TransportConfig
from common.cpu_capability import describe_cpu
from common.run_dir import RunDir
from common.transport import free_port, loopback_endpoint, open_session, subscribe
from common.keys import Keys
from common.wire.envelope import decode
from common.wire.messages import EpisodeRecord, ReplayStats
from common.wire.metrics import LearnerStats
from replay.recorder.reader import LogFile

ROOT = Path(__file__).resolve().parents[2]
RUN_TIMEOUT_S = 900.0
NEVER = 10**12  # a learner budget the runs never reach: the bench decides when a run ends


def rate(samples: list[tuple[float, int]], low: int, high: int) -> float:
    """Steps per second between the first (time, steps) samples at or past `low` and `high` steps."""
    first = next((t, s) for t, s in samples if s >= low)
    last = next((t, s) for t, s in samples if s >= high)
    return (last[1] - first[1]) / max(last[0] - first[0], 1e-9)


class Watch:
    """The replay's step count, the moment the actor first acts with the network, the learner's rate."""

    def __init__(self, steps: int) -> None:
        self.steps = steps
        self.lock = threading.Lock()
        self.samples: list[tuple[float, int]] = []
        self.network_from: int | None = None  # replay steps when the first network-driven episode came
        self.updates_per_s: list[float] = []
        self.done = threading.Event()

    def on_replay(self, message: ReplayStats, key: str) -> None:
        with self.lock:
            self.samples.append((message.time, message.env_steps_total))
            if self.network_from is not None and self.samples[-1][1] >= self.network_from + self.steps:
                self.done.set()

    def on_metric(self, message, key: str) -> None:
        with self.lock:
            if isinstance(message, EpisodeRecord) and message.epsilon < 1.0 and self.network_from is None:
                self.network_from = self.samples[-1][1] if self.samples else 0
            elif isinstance(message, LearnerStats) and self.network_from is not None and not self.done.is_set():
                self.updates_per_s.append(message.updates_per_s)


def run_stack(steps: int, record: bool, runs_dir: Path, name: str, extra: list[str]) -> dict:
    port = free_port()
    command = [sys.executable, "deploy/launcher/stack.py", "--preset", "smoke", "--actors", "1", "--port", str(port),
               "--run.name", name, "--run.runs_dir", str(runs_dir), "--pace.total_env_steps", str(NEVER),
               "--recorder.enabled", "true" if record else "false", *extra]
    watch = Watch(steps)
    stack = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)
    keys = Keys("d3rqn", name)
    config = TransportConfig(mode="client", connect=[loopback_endpoint(port)], connect_timeout_s=30)
    with open_session(config) as session:
        subscriptions = [subscribe(session, keys.replay_stats, watch.on_replay, expected=ReplayStats),
                         subscribe(session, keys.metrics_all, watch.on_metric)]
        finished = watch.done.wait(RUN_TIMEOUT_S)
        for subscription in subscriptions:
            subscription.undeclare()
    stack.send_signal(signal.SIGINT)
    code = stack.wait(RUN_TIMEOUT_S)
    if not finished or code != 0:
        raise SystemExit(f"the run did not reach {steps} network-driven steps or the stack failed (exit {code}); "
                         f"see {RunDir(runs_dir / name).logs}")
    with watch.lock:
        samples = sorted(watch.samples)
        result = {"steady": rate(samples, watch.network_from, watch.network_from + steps),
                  "random": rate(samples, 1, watch.network_from) if watch.network_from > 0 else float("nan"),
                  "updates_per_s": statistics.mean(watch.updates_per_s) if watch.updates_per_s else float("nan")}
    if record:
        result.update(log_sizes(RunDir(runs_dir / name).wire_log, name))
    return result


def log_sizes(path: Path, run: str) -> dict:
    """File size, the bytes of its Weights messages and the env steps the log holds."""
    with LogFile(path) as log:
        keys = Keys("d3rqn", run)
        weights = [keys.weights] if keys.weights in log.wire_topics() else []
        weights_bytes = sum(len(record.data) for record in log.records(weights)) if weights else 0
        replay = list(log.records([keys.replay_stats]))
        logged_steps = decode(replay[-1].data, ReplayStats).env_steps_total if replay else 0
        return {"file_bytes": log.size_bytes, "weights_bytes": weights_bytes,
                "weights": log.message_counts.get(keys.weights, 0), "logged_steps": logged_steps}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=3000,
                        help="env steps measured once the actor acts with the network; then the run is stopped")
    parser.add_argument("--rounds", type=int, default=2, help="pairs of runs, recorder on and off, in turns first")
    argv = sys.argv[1:]
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    args = parser.parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    print(f"CPU: {describe_cpu()}", flush=True)
    print(f"stack: smoke preset, 1 actor, {args.steps:,d} env steps measured per run, {args.rounds} rounds"
          + (f", stack flags {' '.join(extra)}" if extra else ""), flush=True)
    with tempfile.TemporaryDirectory() as runs_dir:
        for round_index in range(args.rounds):
            for record in ((True, False) if round_index % 2 == 0 else (False, True)):  # neither always goes first
                name = f"bench{round_index}{'rec' if record else 'off'}"
                result = run_stack(args.steps, record, Path(runs_dir), name, extra)
                line = (f"round {round_index + 1}, recorder {'on ' if record else 'off'}: env steps/s "
                        f"{result['steady']:6.1f} acting with the network ({result['random']:6.1f} random), "
                        f"learner {result['updates_per_s']:4.2f} updates/s")
                if record:
                    per_k = 1000 / result["logged_steps"]
                    line += (f"; log {result['file_bytes'] / 2**20:.1f} MB for {result['logged_steps']:,d} steps: "
                             f"{result['file_bytes'] * per_k / 2**20:.2f} MB per 1,000 env steps, "
                             f"{(result['file_bytes'] - result['weights_bytes']) * per_k / 2**20:.2f} MB without "
                             f"its {result['weights']} weights")
                print(line, flush=True)


if __name__ == "__main__":
    main()
