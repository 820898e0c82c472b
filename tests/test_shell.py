"""The service shell (common/shell.py): a role stops cleanly on SIGTERM or SIGHUP with its liveliness
token gone, a session that cannot open is one clear line and exit code 1, and leaving the
session by an error still closes everything, in order, and a second process for one token is
refused. Every session lives in its own process."""

import multiprocessing
import os
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import zenoh

from common.config_values import load_config
from common.shell import PARENT_ENV, Shell, first_claim, stop_with_parent
from tests.processes import from_a_terminal, loopback_endpoint, start, stop, wait_for
from tests.zenoh_peer import PATH as PEER, read_lines

ROOT = Path(__file__).resolve().parents[1]
RUN = "shell"
ROLES = {"replay": ["-m", "replay.main"], "recorder": ["-m", "replay.recorder.cli", "record"]}


def run_flags(tmp_path, *transport: str) -> list[str]:
    return ["--preset", "smoke", "--run.name", RUN, "--run.runs_dir", str(tmp_path / "runs"), *transport]


# SIGHUP: the terminal of a role started by hand closed; it stops as on SIGTERM (the learner checkpoints)
@pytest.mark.parametrize("role, signum", [("recorder", signal.SIGTERM), ("replay", signal.SIGTERM),
                                          ("replay", signal.SIGHUP)])
def test_a_role_stops_on_sigterm_or_sighup_and_its_token_goes(tmp_path, role, signum):
    endpoint = loopback_endpoint()
    tokens, role_log = tmp_path / "alive.jsonl", tmp_path / f"{role}.log"
    observer = start([str(PEER), "alive", str(tokens), *run_flags(tmp_path, "--transport.listen", endpoint)],
                     tmp_path / "observer.log")
    process = None
    try:
        wait_for(lambda: read_lines(tokens), "the observer's session", 30, [tmp_path / "observer.log"])
        process = start([*ROLES[role], *run_flags(tmp_path, "--transport.connect", endpoint)], role_log)
        token = f"d3rqn/{RUN}/alive/{role}/0"
        changes = lambda: [(line["key"], line["up"]) for line in read_lines(tokens) if line["kind"] == "alive"]
        wait_for(lambda: (token, True) in changes(), f"the {role}'s token", 30, [role_log])
        process.send_signal(signum)
        assert process.wait(30) == 0
        wait_for(lambda: changes()[-1:] == [(token, False)], f"the {role}'s token to go", 10, [role_log])
    finally:
        stop(*[p for p in (process, observer) if p is not None])
    text = role_log.read_text()
    assert "stopped" in text.splitlines()[-1] and "Traceback" not in text
    assert re.search(r"Zenoh session [0-9a-f]{16,32} open", text)  # the name Zenoh's own errors give it


def test_a_bad_endpoint_is_one_line_and_exit_code_1(tmp_path):
    log = tmp_path / "replay.log"
    process = start(["-m", "replay.main", *run_flags(tmp_path, "--transport.listen", "tcp/no-such-host.invalid:7447")],
                    log)
    try:
        assert process.wait(30) == 1
    finally:
        stop(process)
    errors = [line for line in log.read_text().splitlines() if " ERROR " in line]
    assert len(errors) == 1 and "Traceback" not in log.read_text()
    assert " replay ERROR " in errors[0] and ".rs:" not in errors[0]
    assert "cannot open the Zenoh session (mode peer, listen tcp/no-such-host.invalid:7447, connect none)" in errors[0]


def test_a_role_that_crashes_in_native_code_leaves_its_python_stacks_in_its_log(tmp_path):
    log = tmp_path / "replay.log"
    process = start(["-m", "replay.main", *run_flags(tmp_path, "--transport.listen", loopback_endpoint())], log)
    try:
        wait_for(lambda: re.search(r"Zenoh session [0-9a-f]+ open", log.read_text()), "the replay's session", 60, [log])
        process.send_signal(signal.SIGABRT)  # as a Rust abort or a failed assertion in C would
        assert process.wait(30) == -signal.SIGABRT
    finally:
        stop(process)
    text = log.read_text()
    assert "Fatal Python error: Aborted" in text and 'File "' in text and "most recent call first" in text


def leave_by_raising(endpoint: str, events) -> None:
    """In a spawned process: two on_close callbacks, then the role fails inside the session."""
    service = Shell("probe", load_config("smoke", overrides={"run.name": RUN, "transport.listen": [endpoint]}))
    try:
        with service.session() as session:
            service.on_close(lambda: events.put(("first", service.stop.is_set(), session.is_closed())))
            service.on_close(lambda: events.put(("second", service.stop.is_set(), session.is_closed())))
            raise RuntimeError("the role failed")
    except RuntimeError:
        events.put(("after", service.stop.is_set(), session.is_closed()))


def test_leaving_by_an_error_sets_stop_runs_the_callbacks_newest_first_then_closes():
    context = multiprocessing.get_context("spawn")
    events = context.Queue()
    child = context.Process(target=leave_by_raising, args=(loopback_endpoint(), events))
    child.start()
    try:
        seen = [events.get(timeout=30) for _ in range(3)]
    finally:
        child.join(30)
        if child.is_alive():
            child.kill()
    assert seen == [("second", True, False), ("first", True, False), ("after", True, True)]
    assert child.exitcode == 0


def test_a_role_started_by_a_stack_stops_when_the_stack_is_killed(tmp_path):
    """The stack sets D3RQN_STOP_WITH_PARENT to its pid: a role whose stack dies (SIGKILL, a crash) stops by
    itself instead of running on alone. A shell stands in for the stack, a small Python process for the role."""
    role = ("import threading; from common.shell import stop_with_parent; stop = threading.Event(); "
            "stop_with_parent(stop); print('up', flush=True); stop.wait(60); print('stopped', flush=True)")
    out = tmp_path / "role.out"
    stack = subprocess.Popen(["/bin/sh", "-c", f'{PARENT_ENV}=$$ "{sys.executable}" -c "{role}" > "{out}" & wait'],
                             cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    wait_for(lambda: out.exists() and "up" in out.read_text(), "the role's start", 60)
    stack.kill()
    stack.wait()
    wait_for(lambda: "stopped" in out.read_text(), "the role to stop after its stack", 5)


def test_without_a_stack_a_role_watches_no_parent(monkeypatch):
    monkeypatch.delenv(PARENT_ENV, raising=False)
    assert stop_with_parent(threading.Event()) is None


NOHUP_PROBE = """
import signal
from common.shell import on_stop_signals
on_stop_signals(lambda *_: None)
print(signal.getsignal(signal.SIGHUP) == signal.SIG_IGN, signal.getsignal(signal.SIGINT) == signal.default_int_handler,
      signal.getsignal(signal.SIGTERM) == signal.SIG_DFL)
"""


@pytest.mark.parametrize("nohup", [True, False])
def test_the_stop_signals_leave_a_hangup_ignored_by_nohup_ignored(nohup):
    """Every process of a run (roles, stack, main job, grid runner) takes its stop signals here."""
    ignore = (lambda: signal.signal(signal.SIGHUP, signal.SIG_IGN)) if nohup else from_a_terminal
    result = subprocess.run([sys.executable, "-c", NOHUP_PROBE], capture_output=True, text=True, cwd=ROOT,
                            preexec_fn=ignore, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == [str(nohup), "False", "False"]


def hub(tmp_path):
    """The hub, as in a run: a router the roles connect to as clients, noting the tokens' changes; its endpoint
    and a reader of the ups and downs of a token so far."""
    endpoint = loopback_endpoint()
    tokens = tmp_path / "alive.jsonl"
    observer = start([str(PEER), "alive", str(tokens), *run_flags(tmp_path, "--transport.listen", endpoint,
                                                                  "--transport.mode", "router")],
                     tmp_path / "observer.log")
    try:
        wait_for(lambda: read_lines(tokens), "the observer's session", 30, [tmp_path / "observer.log"])
    except BaseException:
        stop(observer)
        raise
    ups = lambda token: [line["up"] for line in read_lines(tokens) if line["kind"] == "alive" and line["key"] == token]
    return observer, endpoint, ups


def test_a_second_replay_of_a_run_waits_for_the_first_to_go_then_is_refused_or_takes_over(tmp_path):
    """One process per token: a second replay of the run waits SOLE_WAIT_S for the first's token to go (a killed
    one's lingers until Zenoh's lease ends), then exits 1 with one line, leaving the first and its snapshot
    alone; a third (--resume), started while the first is alive, takes over once the first is killed, and
    only then reads the snapshot."""
    observer, endpoint, token_ups = hub(tmp_path)
    replay = lambda name, *flags: start(["-m", "replay.main", *run_flags(tmp_path, "--transport.connect", endpoint,
                                                                        "--transport.mode", "client",
                                                                        "--replay.snapshot_period_s", "1"), *flags],
                                        tmp_path / f"{name}.log")
    manifest = tmp_path / "runs" / RUN / "replay" / "snapshot" / "manifest.msgpack"
    token = f"d3rqn/{RUN}/alive/replay/0"
    ups = lambda: token_ups(token)
    processes = []
    try:
        processes.append(first := replay("first"))
        wait_for(lambda: ups() == [True] and manifest.exists(), "the first replay's token and snapshot", 30,
                 [tmp_path / "first.log"])
        processes.append(second := replay("second"))
        assert second.wait(60) == 1
        assert "removing" not in (tmp_path / "second.log").read_text()  # the first's snapshot stays
        errors = [line for line in (tmp_path / "second.log").read_text().splitlines() if " ERROR " in line]
        assert len(errors) == 1 and f"another process holds {token}" in errors[0] and "--run.name" in errors[0]
        assert first.poll() is None and ups() == [True]
        processes.append(third := replay("third", "--resume"))
        wait_for(lambda: "waiting up to" in (tmp_path / "third.log").read_text(), "the third to wait", 30)
        first.kill()
        wait_for(lambda: ups() == [True, False, True], "the third replay's token", 30, [tmp_path / "third.log"])
        assert third.poll() is None
        lines = (tmp_path / "third.log").read_text().splitlines()
        waited, restored = (next(i for i, line in enumerate(lines) if text in line)
                            for text in ("waiting up to", "restored 0 episodes from the snapshot"))
        assert waited < restored  # it read the snapshot the first wrote last, once the first was gone
        third.send_signal(signal.SIGTERM)
        assert third.wait(30) == 0
    finally:
        stop(*processes, observer)


def claim_together(endpoint: str, barrier, events) -> None:
    """In a spawned process: a learner that checks its token at the moment its twin does, then takes a few
    seconds to set up (reading a checkpoint) before it declares the token, and holds it until told."""
    config = load_config("smoke", overrides={"run.name": RUN, "transport.connect": [endpoint],
                                             "transport.mode": "client"})
    service = Shell("learner", config)
    barrier.wait(30)
    try:
        service.claim()
    except SystemExit as refused:
        events.put(("refused", refused.code))
        return
    service.stop.wait(3.0)
    with service.session():
        events.put(("holds", 0))
        service.stop.wait(30.0)


def test_two_learners_checking_at_the_same_moment_leave_one_holding_the_token(tmp_path):
    """Both find the token free at once; each claims it, the lower zid goes on and the other waits, then is
    refused (without the claims both went on, each set up, and both held the token)."""
    observer, endpoint, ups = hub(tmp_path)
    context = multiprocessing.get_context("spawn")
    barrier, events = context.Barrier(2), context.Queue()
    twins = [context.Process(target=claim_together, args=(endpoint, barrier, events)) for _ in range(2)]
    try:
        for twin in twins:
            twin.start()
        seen = sorted(events.get(timeout=60) for _ in twins)
        token_seen = ups(f"d3rqn/{RUN}/alive/learner/0")
    finally:
        for twin in twins:
            twin.kill()
            twin.join(10)
        stop(observer)
    assert seen == [("holds", 0), ("refused", 1)] and token_seen == [True]


def test_a_claim_goes_on_only_ahead_of_every_other_claim_and_never_beside_the_token():
    token = "d3rqn/r/alive/learner/0"
    own = f"{token}/claim/0b"
    assert first_claim([], token, None) and first_claim([own], token, own)
    assert not first_claim([token], token, None) and not first_claim([f"{token}/claim/0c"], token, None)
    assert first_claim([own, f"{token}/claim/c"], token, own)  # 0xc > 0xb: the other withdraws
    assert not first_claim([own, f"{token}/claim/a"], token, own)
    assert not first_claim([own, token], token, own)  # a holder up already
    assert not first_claim([own, f"{token}/claim/zz"], token, own)  # a key nobody can rank counts as held


def test_a_session_that_cannot_say_who_holds_a_token_lets_the_role_go_on(caplog):
    """The check asks the router; an error there (a closed session, a refusing router) is a warning, not a crash."""
    from common.shell import _held_elsewhere

    class Refusing:
        def liveliness(self):
            return self

        def get(self, key, timeout):
            raise zenoh.ZError("session closed")

    with caplog.at_level("WARNING"):
        assert _held_elsewhere(Refusing(), "d3rqn/r/alive/learner/0") is False
    assert "cannot ask whether another process holds d3rqn/r/alive/learner/0 (session closed)" in caplog.text


ENDING = """
import atexit, sys, threading, time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from common.shell import run_main
out = Path(sys.argv[1])

class Finalized:  # its finalizer runs only where the interpreter tears its modules down
    def __del__(self):
        (out / "finalized").write_text("yes")

kept, pools = Finalized(), []
atexit.register(lambda: (out / "atexit").write_text("ran"))

def main():
    late = threading.Thread(target=lambda: (time.sleep(0.3), (out / "thread").write_text("joined")))
    late.start()  # not a daemon: the interpreter would wait for it, and so does run_main
    pools.append(ThreadPoolExecutor(1))
    pools[0].submit(time.sleep, 0.01).result()  # its idle worker waits for the interpreter's word to end
    print("printed, not yet flushed", end="")
    ending = sys.argv[2]
    if ending == "return":
        return 3
    raise SystemExit(None if ending == "none" else ending)

run_main(main)
"""


@pytest.mark.parametrize("ending, code", [("return", 3), ("none", 0), ("gone wrong", 1)])
def test_a_role_ends_with_its_code_threads_joined_exit_handlers_run_and_no_finalization(tmp_path, ending, code):
    script = tmp_path / "ending.py"
    script.write_text(ENDING)
    done = subprocess.run([sys.executable, str(script), str(tmp_path), ending], cwd=ROOT, capture_output=True,
                          text=True, timeout=60, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == code and done.stdout == "printed, not yet flushed"
    assert (ending == "gone wrong") == ("gone wrong" in done.stderr)
    assert (tmp_path / "thread").read_text() == "joined" and (tmp_path / "atexit").read_text() == "ran"
    # no teardown: there Zenoh's threads, refused the GIL, abort the process (common/shell.py run_main)
    assert not (tmp_path / "finalized").exists()
