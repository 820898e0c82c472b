"""The replay process: its Zenoh session and threads (reply, acknowledgement, snapshot), the resume from
its snapshot and counters, the memory check at start, and the status lines and stats it reports. The
service itself (the store, the rate limiter and the requests behind one lock) is replay/service.py.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from pathlib import Path

from common.atomic_file import remove_dead_temporaries, write_text_atomically
from common.config import Config
from common.disk_space import RetriedWrites
from common.logs import Every
from common.run_dir import RunDir
from common.shell import Shell
from common.transport import publisher, put_once, serve_deferred, subscribe
from common.wire.messages import ReplayStats
from replay.acks import AckBook
from replay.memory_budget import KILOBYTE, MEGABYTE
from replay.service import ReplayService
from replay.snapshot import SnapshotError

log = logging.getLogger("replay")

REPLY_THREADS = 2
ACK_PERIOD_S = 0.2  # how often the words on episodes go out (replay/acks.py)


def counters_path(config: Config) -> Path:
    """Where the replay keeps its rate limiter's counters, in the run folder."""
    return RunDir.of(config).replay_counters


def save_counters(path: Path, state: dict) -> Path:
    """Atomic: a temporary file renamed over the old one."""
    return write_text_atomically(path, json.dumps(state))


SPEED_COUNTERS = ("inserted", "traces_served", "env_steps_total")  # the replay's counters given per second too


class CounterSpeeds:
    """How fast growing counters grew, per second, between two looks (the replay's stats)."""

    def __init__(self, clock=time.monotonic) -> None:
        self._clock = clock
        self._last_time = clock()
        self._last: dict[str, float] = {}

    def speeds(self, counters: dict[str, float], names: tuple[str, ...]) -> dict[str, float]:
        now = self._clock()
        elapsed = max(now - self._last_time, 1e-9)
        speeds = {f"{name}_per_s": (counters[name] - self._last.get(name, 0)) / elapsed for name in names}
        self._last_time, self._last = now, dict(counters)
        return speeds


def physical_memory_bytes() -> int | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


def run_replay(config: Config, resume: bool = False) -> None:
    """Serves until SIGINT/SIGTERM; with resume, restores the run's snapshot and counters."""
    shell = Shell("replay", config)
    shell.claim()  # before the snapshot is read: a replay that is stopping writes it last
    remove_dead_temporaries(RunDir.of(config).replay_counters.parent)  # the snapshot's folder lies inside
    stop = shell.stop
    service = ReplayService(config)
    path = counters_path(config)
    if resume:
        _resume(service, path)
    elif service.snapshotter.exists:
        log.info("a fresh start: removing the run's earlier snapshot in %s (replay --resume restores it)",
                 service.snapshotter.directory)
        service.snapshotter.clear()
    _check_budget_at_start(service, config)
    keys = shell.keys
    max_bytes = int(config.replay.max_message_mb * MEGABYTE)
    with shell.session() as session:
        # no expected type: a message of another type reaches the service, which counts it
        receivers = {"episodes": subscribe(session, keys.episodes, service.on_episode, max_bytes=max_bytes),
                     "exploration": subscribe(session, keys.exploration, service.on_exploration),
                     "requests": serve_deferred(session, keys.replay_sample, service.on_sample_request)}
        for receiver in receivers.values():
            shell.on_close(receiver.undeclare)
        stats_out = publisher(session, keys.replay_stats)
        rate_out = publisher(session, keys.replay_rate)

        threads = [threading.Thread(target=service.serve_pending, args=(stop, rate_out.put if n == 0 else None),
                                    name=f"reply-{n}", daemon=True) for n in range(REPLY_THREADS)]
        threads.append(threading.Thread(target=_send_acks, args=(stop, service.acks, session, keys), name="acks",
                                        daemon=True))
        if config.replay.snapshot_period_s > 0:
            threads.append(threading.Thread(target=_snapshot_every, args=(stop, service, config), name="snapshot",
                                            daemon=True))
        for thread in threads:
            thread.start()
        log.info("serving run %r: capacity %d episodes, budget %.0f MB, traces of %d steps, "
                 "1 update per %g env steps within %g updates; %s", config.run.name, config.replay.capacity,
                 config.replay.memory_budget_mb, config.learner.trace_length, config.pace.env_steps_per_update,
                 config.pace.error_buffer_updates,
                 f"a snapshot every {config.replay.snapshot_period_s:g} s to {service.snapshotter.directory}"
                 if config.replay.snapshot_period_s > 0 else "no snapshots")
        _report_until(stop, service, receivers, stats_out, config, path)
        for thread in threads:
            thread.join(timeout=5.0)
        service.drop_pending()
    if config.replay.snapshot_period_s > 0 and service.write_snapshot():
        log.info("final snapshot: %d episodes, %d bytes", service.snapshot_stats["snapshot_episodes"],
                 service.snapshot_stats["snapshot_bytes"])
    try:
        save_counters(path, service.limiter_state())
    except OSError as error:
        log.warning("cannot save the rate limiter's counters to %s: %s", path, error)
    _log_stats(service.stats(), "stopped; ")


def _send_acks(stop: threading.Event, acks: AckBook, session, keys) -> None:
    while not stop.wait(ACK_PERIOD_S):
        for ack in acks.drain():
            try:
                put_once(session, keys.episode_acks(ack.actor_id), ack)
            except Exception as error:  # the actor sends the episode again; the sender must go on
                log.warning("could not acknowledge episodes of actor %d: %s", ack.actor_id, error)


def _snapshot_every(stop: threading.Event, service: ReplayService, config: Config) -> None:
    while not stop.wait(config.replay.snapshot_period_s):
        try:
            service.write_snapshot()
        except Exception:  # a snapshot thread that died would stop snapshots for good
            log.exception("the snapshot failed; the next one is tried in %g s", config.replay.snapshot_period_s)


def _read_counters(path: Path) -> dict | None:
    try:
        state = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as error:
        log.warning("--resume: cannot read the counters in %s (%s)", path, error)
        return None
    return state if isinstance(state, dict) else None


def _resume(service: ReplayService, path: Path) -> None:
    """The snapshot's episodes and counters, with the newest rate limiter counters of the two files."""
    counters = _read_counters(path)
    try:
        restored = service.snapshotter.load(service.shape.frame_shape)
    except SnapshotError as error:
        log.warning("--resume: %s; the store starts empty", error)
        restored = None
    if restored is not None:
        try:
            source = service.restore(restored, counters)
        except ValueError as error:
            log.warning("--resume: cannot use the snapshot in %s (%s); the store starts empty",
                        service.snapshotter.directory, error)
        else:
            limiter = service.limiter
            log.info("restored %d episodes from the snapshot in %s, taken %.0f s ago (%d records skipped); rate "
                     "limiter counters from %s: %d env steps, %d batches served, start mark %s; %d episodes "
                     "missing so far", len(service.store), service.snapshotter.directory,
                     time.time() - restored.taken, restored.skipped, source, limiter.env_steps, limiter.served,
                     "none" if limiter.start_mark is None else f"{limiter.start_mark:.0f}", service.ledger.missing)
            return
    if counters is None:
        log.warning("--resume: no snapshot and no counters at %s; counting this run's env steps and batches "
                    "from zero", path)
        return
    try:
        service.load_limiter_state(counters)
    except ValueError as error:
        log.warning("--resume: cannot use the counters in %s (%s); counting from zero", path, error)
        return
    limiter = service.limiter
    log.info("resumed the rate limiter from %s: %d env steps, %d batches served, start mark %s%s", path,
             limiter.env_steps, limiter.served, "none" if limiter.start_mark is None else f"{limiter.start_mark:.0f}",
             f"; no snapshot, the store is empty: batches wait until it holds {limiter.limit.start_episodes} "
             "episodes again (the refill's steps are not owed)" if limiter.refilling else "")


def _check_budget_at_start(service: ReplayService, config: Config) -> None:
    service.budget_report(config.replay.frame_kb_estimate * KILOBYTE, "replay.frame_kb_estimate")
    memory = physical_memory_bytes()
    if memory is not None and config.replay.memory_budget_mb * MEGABYTE > memory:
        log.warning("replay.memory_budget_mb %.0f exceeds this machine's %.0f MB of memory: a full buffer "
                    "would not fit", config.replay.memory_budget_mb, memory / MEGABYTE)


def _report_until(stop: threading.Event, service: ReplayService, receivers: dict, stats_out, config: Config,
                  path: Path) -> None:
    meter = CounterSpeeds()
    log_every = Every(config.replay.log_period_s)
    counters = RetriedWrites("rate limiter's counters", path, log)  # a full disk: said once, not every period
    while not stop.wait(config.replay.stats_period_s):
        # messages that are not wire messages or whose fields are invalid, refused before the service saw them
        malformed = {f"malformed_{door}": receiver.rejected for door, receiver in receivers.items()}
        stats = service.stats(rejected={**malformed, "rejected_messages": receivers["episodes"].rejected})
        stats.speeds = meter.speeds({name: getattr(stats, name) for name in SPEED_COUNTERS}, SPEED_COUNTERS)
        stats_out.put(stats)
        counters.attempt(lambda: save_counters(path, service.limiter_state()))
        if log_every.due():
            _log_stats(stats)


def _log_stats(stats: ReplayStats, lead: str = "") -> None:
    rate, snapshot = stats.rate, stats.snapshot.get("snapshot_episodes", "no")
    age = "" if stats.snapshot_age_s is None else f" {stats.snapshot_age_s:.0f} s ago"
    log.info("%sepisodes %d (%d B), env steps %d, inserted %d, traces served %d, short %d, malformed %d, rejected %d, "
             "missing %d; snapshot %s episodes%s; updates due %.1f, batches served %d, actors hold: %s",
             lead, stats.episodes, stats.bytes, stats.env_steps_total, stats.inserted, stats.traces_served,
             stats.short_dropped, stats.rejected.get("rejected_messages", 0), stats.rejected.get("rejected_total", 0),
             stats.episodes_missing, snapshot, age, rate.updates_due, rate.batches_served, rate.hold_reason or "no")
