"""An actor that hears no word from the replay (common/hub_link.py): it holds its next episode after
actor.silence_hold_s, reopens its Zenoh session after actor.silence_reopen_s (and again after each
further span), and drives again on the fresh session once the word comes back. The replay is a stand-in
(tests/zenoh_peer.py voice) that goes quiet while a file exists; a watcher records what arrives."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

from common.hub_link import keep_hearing
from actor.mailbox import Mailbox
from tests.processes import loopback_endpoint, start, stop, wait_for
from tests.zenoh_peer import PATH as PEER, read_lines
from wire_examples import example_rate
from fake_clock import FakeClock

HOLD_S, REOPEN_S = 1.0, 3.0



def test_the_mailbox_holds_once_the_replays_word_has_not_come_for_the_silence_span():
    clock = FakeClock(100.0)
    mailbox = Mailbox(silence_hold_s=30.0, clock=clock)
    clock.now += 1000
    assert mailbox.must_hold() == "" and mailbox.silent_s() == 0.0  # no word yet: the actor waits for one anyway
    mailbox.offer_rate(example_rate())
    clock.now += 30.0
    assert mailbox.must_hold() == "" and mailbox.silent_s() == 30.0
    clock.now += 0.5
    assert mailbox.must_hold() == "silent"
    mailbox.offer_rate(example_rate(hold_reason="behind"))  # heard again: the replay's own word rules
    assert mailbox.must_hold() == "behind"
    clock.now += 31.0
    mailbox.replay_gone()
    assert mailbox.must_hold() == "replay"  # a replay known gone says more than its silence
    assert Mailbox(clock=clock).must_hold() == ""  # silence_hold_s None: never


class CountingLink:
    def __init__(self) -> None:
        self.reopened, self.role = 0, "actor"

    def reopen(self) -> bool:
        self.reopened += 1
        return True


class Script(threading.Event):
    """A stop event whose every wait is one poll: it steps the silence through `silences`, then stops."""

    def __init__(self, silences: list[float]) -> None:
        super().__init__()
        self.silences, self.at = silences, -1

    def wait(self, timeout=None) -> bool:
        self.at += 1
        return self.at >= len(self.silences)

    def silent_s(self) -> float:
        return self.silences[self.at]


def test_the_session_reopens_at_each_multiple_of_the_span_and_the_count_restarts_after_a_word():
    link = CountingLink()
    script = Script([10, 59, 60, 61, 100, 119, 120, 130, 2, 59, 60])
    keep_hearing(link, script.silent_s, 60.0, script)
    assert link.reopened == 3  # at 60 and 120 (not at 130), and at 60 again after the word came back


def test_an_actor_that_hears_nothing_holds_reopens_its_session_and_drives_again_once_heard(tmp_path):
    endpoint, quiet = loopback_endpoint(), tmp_path / "quiet"
    flags = ["--preset", "smoke", "--run.name", "silence", "--run.runs_dir", str(tmp_path / "runs"),
             "--replay.stats_period_s", "0.2", "--actor.silence_hold_s", str(HOLD_S),
             "--actor.silence_reopen_s", str(REOPEN_S), "--actor.log_period_s", "0.5"]
    client = ["--transport.mode", "client", "--transport.connect", endpoint]
    voice_lines, watch_lines = tmp_path / "voice.jsonl", tmp_path / "watch.jsonl"
    logs = [tmp_path / name for name in ("voice.log", "watch.log", "actor.log")]
    voice = start([str(PEER), "voice", str(voice_lines), "--quiet-file", str(quiet), *flags,
                   "--transport.mode", "router", "--transport.listen", endpoint], logs[0])
    watcher = start([str(PEER), "watch", str(watch_lines), *flags, *client], logs[1])
    actor = None
    try:
        wait_for(lambda: read_lines(voice_lines) and read_lines(watch_lines), "the stand-in replay and the watcher",
                 60, logs)
        actor = start(["-m", "actor.main", *flags, *client], logs[2])
        episodes = lambda: [line for line in read_lines(watch_lines) if line["kind"] == "episode"]
        stats = lambda: [line["values"] for line in read_lines(watch_lines) if line["kind"] == "actor_stats"]
        wait_for(lambda: len(episodes()) >= 3, "the actor's first episodes", 90, logs)
        quiet.touch()
        wait_for(lambda: any(line["kind"] == "quiet" for line in read_lines(voice_lines)), "the replay quiet", 10, logs)
        quiet_at = time.time()
        wait_for(lambda: any(values["sessions_reopened"] >= 2 for values in stats()),
                 "two reopened sessions while the replay is quiet", 60, logs)
        port = int(endpoint.rsplit(":", 1)[1])
        wait_for(lambda: connections_to(actor.pid, port) == 1, "one connection to the router: the old sessions "
                 "closed", 10, logs)
        settled = quiet_at + HOLD_S + 2.0  # the last episodes begun before the hold finish and arrive
        made_before = max(line["index"] for line in episodes() if line["t"] <= settled)
        quiet.unlink()
        spoke_at = time.time()
        # while quiet, only episodes sent again (no acks come from the stand-in) arrive, none begun in the silence
        assert all(line["index"] <= made_before for line in episodes() if settled < line["t"] < spoke_at)
        wait_for(lambda: any(line["index"] > made_before for line in episodes()),
                 "a new episode on the reopened session once the replay speaks again", 60, logs)
        assert stop_returns(actor) == 0
    finally:
        stop(*[process for process in (actor, watcher, voice) if process is not None])
    text = logs[2].read_text()
    assert "this actor may no longer hear the hub; reopening its Zenoh session" in text
    assert text.count("Zenoh session reopened; everything declared again on it") >= 2 and "Traceback" not in text


def test_a_learner_that_hears_nothing_reopens_its_session(tmp_path):
    endpoint, quiet = loopback_endpoint(), tmp_path / "quiet"
    flags = ["--preset", "smoke", "--run.name", "deaf", "--run.runs_dir", str(tmp_path / "runs"),
             "--replay.stats_period_s", "0.2", "--learner.silence_reopen_s", str(REOPEN_S)]
    voice_lines, logs = tmp_path / "voice.jsonl", [tmp_path / "voice.log", tmp_path / "learner.log"]
    voice = start([str(PEER), "voice", str(voice_lines), "--quiet-file", str(quiet), *flags,
                   "--transport.mode", "router", "--transport.listen", endpoint], logs[0])
    learner = None
    try:
        wait_for(lambda: read_lines(voice_lines), "the stand-in replay", 60, logs)
        learner = start(["-m", "learner.main", *flags, "--transport.mode", "client", "--transport.connect", endpoint],
                        logs[1])
        wait_for(lambda: "waiting for" in logs[1].read_text(), "the learner waiting for its first batch", 90, logs)
        time.sleep(2 * REOPEN_S)  # the replay speaks: no reopen
        assert "reopening its Zenoh session" not in logs[1].read_text()
        quiet.touch()
        reopened = lambda: logs[1].read_text().count("Zenoh session reopened; everything declared again on it")
        wait_for(lambda: reopened() >= 2, "two reopened sessions while the replay is quiet", 60, logs)
        port = int(endpoint.rsplit(":", 1)[1])
        wait_for(lambda: connections_to(learner.pid, port) == 1, "one connection to the router: the old sessions "
                 "closed", 10, logs)
        assert stop_returns(learner) == 0
    finally:
        stop(*[process for process in (learner, voice) if process is not None])
    text = logs[1].read_text()
    assert "this learner may no longer hear the hub; reopening its Zenoh session" in text and "Traceback" not in text


def connections_to(pid: int, port: int) -> int:
    """The process's established TCP connections to a port on this host (from /proc)."""
    sockets = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:  # closed meanwhile
            continue
        if target.startswith("socket:["):
            sockets.add(target[8:-1])
    count = 0
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            fields = line.split()
            remote_port, state, inode = int(fields[2].rsplit(":", 1)[1], 16), fields[3], fields[9]
            count += remote_port == port and state == "01" and inode in sockets
    return count


def stop_returns(process) -> int:
    stop(process)
    return process.returncode
