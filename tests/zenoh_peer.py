"""Test peers run as their own processes (Zenoh sessions live only in fresh interpreters), by path
(tests/ is not an installed package):

    python tests/zenoh_peer.py watch OUT.jsonl [config flags]   # what a run publishes, one JSON line each
    python tests/zenoh_peer.py alive OUT.jsonl [config flags]   # the run's liveliness tokens as they come and go
    python tests/zenoh_peer.py probe [config flags]             # exit 0 if a session opens, 3 if not
    python tests/zenoh_peer.py rogue OUT.jsonl --weights-version N [config flags]
    python tests/zenoh_peer.py voice OUT.jsonl --quiet-file PATH [config flags]

`watch` writes a line per EpisodeRecord (actor, weights version), per episode on the episodes
key (actor, the weights versions its steps were acted with), per learner and replay stats (a
few values), per actor stats (all values), per sample of the run whose payload starts with the rogue's marker, and per key
the first time anything else arrives on it. `rogue` forges what only other roles may send:
real weights of the run's network with version N on weights/broadcast (every 0.5 s), marker
bytes on exploration, episodes, replay/stats and replay/rate, and queryables on replay/sample
and weights/latest that count the queries reaching them (writing the counts every 0.5 s). `voice`
stands in for a replay that goes quiet: its liveliness token, and its word on replay/rate (go, before
updates) every replay.stats_period_s except while the file --quiet-file exists (a line each change).
The config flags are the roles' own (--config FILE.toml, --transport.*, ...).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from pathlib import Path

from common.config import Config
from common.config_cli import add_config_arguments, parse_config_or_exit

MARKER = b"ROGUE-D3RQN"
PATH = Path(__file__).resolve()  # run it by path: tests/ is not an installed package


def read_lines(path: Path) -> list[dict]:
    """The JSON lines written so far (for the tests that started a peer)."""
    if not path.exists():
        return []
    lines = []
    for line in path.read_text().splitlines():
        try:
            lines.append(json.loads(line))
        except json.JSONDecodeError:  # a line being written
            pass
    return lines


class Lines:
    """JSON lines to a file, flushed each, from any thread."""

    def __init__(self, path: Path) -> None:
        self._file = open(path, "a", buffering=1)
        self._lock = threading.Lock()

    def write(self, **fields) -> None:
        with self._lock:
            self._file.write(json.dumps({**fields, "t": time.time()}) + "\n")

    def close(self) -> None:
        self._file.close()


def watch(config: Config, out: Lines, stop: threading.Event) -> None:
    from common.transport import open_session, subscribe
    from common.keys import Keys
    from common.wire.messages import Episode, EpisodeRecord, ReplayStats, flat_values
    from common.wire.metrics import ActorStats, LearnerStats

    keys = Keys(config.transport.namespace, config.run.name)

    def on_metric(message, key):
        if isinstance(message, EpisodeRecord):
            out.write(kind="record", actor=message.actor_id, weights_version=message.weights_version,
                      epsilon=message.epsilon)
        elif isinstance(message, LearnerStats):
            out.write(kind="learner", updates=message.updates)
        elif isinstance(message, ActorStats):
            out.write(kind="actor_stats", actor=key.rsplit("/", 1)[-1], values=flat_values(message))

    def on_stats(message, key):
        values = flat_values(message)
        out.write(kind="replay", inserted=values.get("inserted"), env_steps=values.get("env_steps_total"),
                  missing=values.get("episodes_missing"), duplicates=values.get("rejected_episode_duplicate", 0),
                  served=values.get("rate_batches_served"), restored=values.get("restored_episodes"))

    def on_episode(message, key):
        out.write(kind="episode", actor=message.actor_id, steps=len(message), index=message.episode_index,
                  versions=sorted({int(version) for version in message.weights_version}))  # acted with

    seen: set[str] = set()

    def on_any(sample):
        key = str(sample.key_expr)
        if bytes(sample.payload.to_bytes()[:len(MARKER)]) == MARKER:
            out.write(kind="marker", key=key)
        elif key not in seen:
            seen.add(key)
            out.write(kind="key", key=key)

    with open_session(config.transport) as session:
        declared = [subscribe(session, keys.metrics_all, on_metric),
                    subscribe(session, keys.replay_stats, on_stats, expected=ReplayStats),
                    subscribe(session, keys.episodes, on_episode, expected=Episode),
                    session.declare_subscriber(keys.all, on_any)]  # as the recorder does
        out.write(kind="up")
        stop.wait()
        for entity in declared:
            entity.undeclare()


def alive(config: Config, out: Lines, stop: threading.Event) -> None:
    from common.liveliness import watch_liveliness
    from common.transport import open_session
    from common.keys import Keys

    keys = Keys(config.transport.namespace, config.run.name)
    with open_session(config.transport) as session:
        with watch_liveliness(session, keys.liveliness_all, lambda key, up: out.write(kind="alive", key=key, up=up)):
            out.write(kind="up")
            stop.wait()


def probe(config: Config) -> int:
    import zenoh

    from common.transport import open_session
    zenoh.init_log_from_env_or("warn")  # why a link failed: the TLS alert, on stderr (the probe's log)
    try:
        session = open_session(config.transport)
    except zenoh.ZError as error:
        print(f"no session: {error}", flush=True)
        return 3
    print("connected", flush=True)
    session.close()
    return 0


def rogue(config: Config, out: Lines, stop: threading.Event, weights_version: int) -> None:
    import zenoh

    from common.network import D3RQN, weights_to_numpy
    from common.transport import open_session
    from common.keys import Keys
    from common.wire.envelope import encode
    from common.wire.messages import Weights

    keys = Keys(config.transport.namespace, config.run.name)
    weights = encode(Weights(version=weights_version, tensors=weights_to_numpy(D3RQN(config.network)),
                             created=time.time()))
    counts = {"replay_sample_queries": 0, "weights_latest_queries": 0, "weights_sent": 0}
    lock = threading.Lock()

    def counting(name: str, answer: bytes | None):
        def on_query(query):
            with lock:
                counts[name] += 1
            with query:
                if answer is not None:
                    query.reply(query.key_expr, answer)
        return on_query

    with open_session(config.transport) as session:
        block = zenoh.CongestionControl.BLOCK
        weights_out = session.declare_publisher(keys.weights, congestion_control=block)
        forged = [session.declare_publisher(key, congestion_control=block)
                  for key in (keys.exploration, keys.episodes, keys.replay_stats, keys.replay_rate)]
        queryables = [session.declare_queryable(keys.replay_sample, counting("replay_sample_queries", MARKER)),
                      session.declare_queryable(keys.weights_latest, counting("weights_latest_queries", weights))]
        out.write(kind="up")
        while not stop.wait(0.5):
            weights_out.put(weights)
            for publisher in forged:
                publisher.put(MARKER)
            with lock:
                counts["weights_sent"] += 1
                out.write(kind="counts", **counts)
        for entity in [weights_out, *forged, *queryables]:
            entity.undeclare()


def voice(config: Config, out: Lines, stop: threading.Event, quiet_file: Path) -> None:
    from common.liveliness import declare_liveliness
    from common.transport import open_session, publisher
    from common.keys import Keys
    from common.wire.messages import RateState

    keys = Keys(config.transport.namespace, config.run.name)
    word = RateState(time=0.0, env_steps=0, batches_served=0, updates_due=0.0, start_env_steps=None, hold_reason="",
                     closed=False, refilling=False, refill_env_steps=0, lost_updates=0, recounted_updates=0,
                     error_buffer_updates=1.0, hold_updates=0.0, env_steps_per_update_target=4.0,
                     env_steps_per_update=None)
    with open_session(config.transport) as session:
        token = declare_liveliness(session, keys.liveliness("replay", "0"))
        rate_out = publisher(session, keys.replay_rate)
        out.write(kind="up")
        speaking = None
        while not stop.wait(config.replay.stats_period_s):
            if speaking != (not quiet_file.exists()):
                speaking = not speaking
                out.write(kind="speaking" if speaking else "quiet")
            if speaking:
                rate_out.put(word)
        rate_out.undeclare()
        token.undeclare()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="zenoh_peer")
    parser.add_argument("command", choices=("watch", "alive", "probe", "rogue", "voice"))
    parser.add_argument("out", nargs="?", type=Path, help="JSON lines (watch, alive, rogue, voice)")
    parser.add_argument("--weights-version", type=int, default=987_654, help="rogue: the forged weights' version")
    parser.add_argument("--quiet-file", type=Path, help="voice: no word on replay/rate while this file exists")
    add_config_arguments(parser)
    args, config = parse_config_or_exit(parser, argv)
    if args.command == "probe":
        return probe(config)
    from common.shell import stop_on_signals

    out = Lines(args.out)
    stop = stop_on_signals()
    try:
        if args.command == "watch":
            watch(config, out, stop)
        elif args.command == "alive":
            alive(config, out, stop)
        elif args.command == "voice":
            voice(config, out, stop, args.quiet_file)
        else:
            rogue(config, out, stop, args.weights_version)
    finally:
        out.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
