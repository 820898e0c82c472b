"""The main job, deploy/launcher/stack.py: starts the roles, restarts a dead actor, stops cleanly on a hangup,
and keeps the configured update ratio over a whole run."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from common.presets import PRESETS
from tests.processes import children, from_a_terminal, kill_tree, wait_for

STACK = Path(__file__).resolve().parents[1] / "deploy" / "launcher" / "stack.py"


def test_stack_restarts_a_dead_actor_and_stops_cleanly_on_a_hangup(tmp_path):
    """SIGHUP (its terminal closed) stops it as Ctrl-C does, which the other stack tests send."""
    output = open(tmp_path / "stack.out", "wb")
    stack = subprocess.Popen([sys.executable, str(STACK), "--preset", "smoke", "--actors", "1",
                              "--run.runs_dir", str(tmp_path), "--run.name", "main", "--recorder.enabled", "false"],
                             stdout=output, stderr=subprocess.STDOUT, cwd=tmp_path, preexec_fn=from_a_terminal)
    run_dir = tmp_path / "main"
    try:
        actor_log, learner_log = run_dir / "logs" / "actor-0.log", run_dir / "logs" / "learner.log"
        # the actor's first report (not its config dump, which names start_episodes), and a learner
        # past its start-up (its Ctrl-C handler is set): an interrupted import would leave no checkpoint
        wait_for(lambda: actor_log.exists() and "INFO actor: episodes" in actor_log.read_text()
                 and learner_log.exists() and "INFO learner: device" in learner_log.read_text(),
                 "the actor's first report and the learner's start", 120, [tmp_path / "stack.out", actor_log])
        roles = children(stack.pid)
        assert sorted(" ".join(command.split()[2:3]) for command in roles.values()) == \
            ["actor.main", "learner.main", "replay.main"]
        actor_pid = next(pid for pid, command in roles.items() if "actor.main" in command)
        os.kill(actor_pid, signal.SIGKILL)
        wait_for(lambda: any("actor.main" in command and pid != actor_pid
                             for pid, command in children(stack.pid).items()),
                 "a new actor", 60, [tmp_path / "stack.out"])
        assert "actor-0 exited with code -9; restarting it" in (tmp_path / "stack.out").read_text()
        started = list(children(stack.pid))
        stack.send_signal(signal.SIGHUP)
        assert stack.wait(90) == 0
        for pid in started:
            assert not Path(f"/proc/{pid}").exists() or "Z" in Path(f"/proc/{pid}/stat").read_text().split()[2]
        text = (tmp_path / "stack.out").read_text()
        assert "stopping processes" in text and "restarts: actor-0 1;" in text
        assert (run_dir / "config.toml").exists() and (run_dir / "checkpoints" / "latest.pt").exists()
    finally:
        if stack.poll() is None:
            kill_tree(stack)


def test_a_smoke_run_keeps_the_configured_ratio_within_one_percent(tmp_path):
    """The whole run's env steps per update, from the replay's start mark to the learner's last update,
    as the learner's metrics and the run summary give it. The learner ends between 0 and B updates
    past what the steps pay for (B, the smoke preset's error buffer, is 2) and pays for the episodes
    still in flight, so over about 225 updates the ratio lies within 2 / 225 < 1% below 20."""
    budget = 4_500
    output = open(tmp_path / "stack.out", "wb")
    stack = subprocess.Popen([sys.executable, str(STACK), "--preset", "smoke", "--actors", "1",
                              "--run.runs_dir", str(tmp_path), "--run.name", "ratio", "--recorder.enabled", "false",
                              "--pace.total_env_steps", str(budget),
                              # small updates (a small LSTM, 2 traces of 5 steps, one thread on a shared
                              # machine): half a minute, not minutes
                              "--network.lstm_units", "16", "--learner.batch_size", "2",
                              "--learner.trace_length", "5", "--learner.n_mask", "2", "--learner.torch_threads", "1",
                              # and the stored recurrent state (beyond the paper) through every role
                              "--learner.stored_state", "true", "--learner.burn_in", "2"],
                             stdout=output, stderr=subprocess.STDOUT, cwd=tmp_path)
    try:
        assert stack.wait(240) == 0, (tmp_path / "stack.out").read_text()[-3000:]
    finally:
        if stack.poll() is None:
            stack.kill()
            stack.wait()
    summary = json.loads((tmp_path / "ratio" / "summary.json").read_text())
    configured = PRESETS["smoke"]["pace.env_steps_per_update"]
    assert summary["learner_finished"] and summary["env_steps_per_update_configured"] == configured
    assert summary["env_steps"] >= budget and summary["updates"] >= 200
    assert summary["env_steps_per_update"] == pytest.approx(
        (summary["env_steps"] - summary["start_env_steps"]) / summary["updates"])
    assert abs(summary["env_steps_per_update"] / configured - 1) < 0.01, summary
    assert "env steps per update (configured 20)" in (tmp_path / "stack.out").read_text()
    role_logs = " ".join(path.read_text() for path in (tmp_path / "ratio" / "logs").glob("*"))
    assert "rejected (" not in role_logs  # no episode or batch refused (for its state rows, say)


def test_the_stacks_watcher_waits_for_a_slow_router_then_gives_up_with_a_line(monkeypatch, capsys):
    """On a loaded machine the replay may take longer than one connect timeout to listen: the stack retries
    (and, its session opened inside the block that stops the processes, never leaves them behind)."""
    import threading

    from common.config import TransportConfig
    from common.transport import free_port
    from deploy.launcher import stack
    from deploy.launcher.console import Console

    monkeypatch.setattr(stack, "WATCHER_CONNECT_S", 1.0)
    transport = TransportConfig(mode="client", connect=[f"tcp/127.0.0.1:{free_port()}"], connect_timeout_s=0.3)
    started = time.monotonic()
    assert stack.open_watcher(transport, Console(threading.Event())) is None
    assert time.monotonic() - started >= 1.0
    err = capsys.readouterr().err
    assert "waiting for the replay's router" in err and "did not answer within 1 s" in err
    stopped = threading.Event()
    stopped.set()
    assert stack.open_watcher(transport, Console(stopped)) is None


def test_a_stack_whose_reader_is_gone_stops_its_run_cleanly_and_a_second_stack_is_refused(tmp_path):
    """The grid runner killed: the stack's stdout pipe has no reader. The stack stops the run as Ctrl-C
    does (the learner checkpoints) rather than fail on its next line and leave its processes training, and
    while it runs, another stack on the same run folder is refused at once."""
    command = [sys.executable, str(STACK), "--preset", "smoke", "--actors", "1", "--run.runs_dir", str(tmp_path),
               "--run.name", "unread", "--recorder.enabled", "false", "--network.lstm_units", "16",
               "--learner.batch_size", "2", "--learner.trace_length", "5", "--learner.n_mask", "2",
               "--learner.torch_threads", "1", "--pace.total_env_steps", "1000000"]
    stack = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=tmp_path)
    run_dir = tmp_path / "unread"
    learner_log = run_dir / "logs" / "learner.log"
    try:
        lines = [stack.stdout.readline() for _ in range(2)]  # its start line, then its first status line
        first_status = time.monotonic()  # the next comes LOGGED_LINE_PERIOD_S (30 s) later into a pipe
        assert b"env steps" in lines[1], lines
        wait_for(lambda: learner_log.exists() and "INFO learner: device" in learner_log.read_text(),
                 "the learner's start", 60, [learner_log])
        second = subprocess.run(command, capture_output=True, text=True, cwd=tmp_path, timeout=60)
        assert second.returncode == 2 and "is in use by another stack" in second.stderr, second.stderr
        roles = list(children(stack.pid))
        assert len(roles) == 3  # replay, learner, actor
        stack.stdout.close()  # nobody reads the stack any more
        stack.wait(90)
        # noticed without a line to write: the stop came before the next status line was due
        assert time.monotonic() - first_status < 25
        for pid in roles:
            assert not Path(f"/proc/{pid}").exists() or "Z" in Path(f"/proc/{pid}/stat").read_text().split()[2]
        assert json.loads((run_dir / "status.json").read_text())["phase"] == "stopped"
        assert (run_dir / "checkpoints" / "latest.pt").exists() and (run_dir / "summary.json").exists()
    finally:
        if stack.poll() is None:
            kill_tree(stack)


def gone(pid: int) -> bool:
    return not Path(f"/proc/{pid}").exists() or "Z" in Path(f"/proc/{pid}/stat").read_text().split()[2]


def test_a_stack_whose_main_job_is_killed_stops_its_run_cleanly(tmp_path):
    """The main job (deploy/main_job.py) killed by SIGKILL, whose stack writes to the terminal and would
    otherwise train on alone: the stack sees its parent gone and stops as on Ctrl-C (the learner checkpoints)."""
    flags = ["--preset", "smoke", "--actors", "1", "--run.runs_dir", str(tmp_path), "--run.name", "orphan",
             "--recorder.enabled", "false", "--network.lstm_units", "16", "--learner.batch_size", "2",
             "--learner.trace_length", "5", "--learner.n_mask", "2", "--learner.torch_threads", "1",
             "--pace.total_env_steps", "1000000"]
    output = open(tmp_path / "job.out", "wb")
    job = subprocess.Popen([sys.executable, "-c", "import sys; from deploy.main_job import call; "
                            f"call([sys.executable, {str(STACK)!r}, *{flags!r}])"],
                           stdout=output, stderr=subprocess.STDOUT, cwd=STACK.parents[1])
    run_dir, stack_pid = tmp_path / "orphan", None
    learner_log = run_dir / "logs" / "learner.log"
    try:
        wait_for(lambda: learner_log.exists() and "INFO learner: device" in learner_log.read_text(),
                 "the learner's start", 120, [tmp_path / "job.out"])
        stack_pid = next(pid for pid, command in children(job.pid).items() if "stack.py" in command)
        roles = list(children(stack_pid))
        job.kill()
        job.wait()
        wait_for(lambda: gone(stack_pid), "the stack to stop after its job", 90, [tmp_path / "job.out"])
        assert all(gone(pid) for pid in roles) and len(roles) == 3
        assert json.loads((run_dir / "status.json").read_text())["phase"] == "stopped"
        assert (run_dir / "checkpoints" / "latest.pt").exists()
        assert "is gone: stopping" in (tmp_path / "job.out").read_text()
    finally:
        for pid in [stack_pid, *(children(stack_pid) if stack_pid else [])]:
            if pid is not None and not gone(pid):
                os.kill(pid, signal.SIGKILL)
