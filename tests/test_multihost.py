"""docs/deployment.md "Across machines" for real: three hosts as Linux network namespaces on one switch.

    hub  10.203.0.1   replay (router) + learner, from deploy/configs/hub-replay.toml and hub-learner.toml
    a1   10.203.0.11  actor 1, from remote-actor.toml with --transport.connect tcp/10.203.0.1:7447
    a2   10.203.0.12  actor 2, the same
    sw                a bridge; each host's eth0 is one end of a veth pair whose other end is a port of it

Each host has only its loopback and its eth0, so an actor reaches the hub over its veth link
and the bridge, as it would over a LAN; the configs' fixed port 7447 is free in every
namespace. The secure variant runs the deploy/configs/secure-*.toml files the same way (TLS,
mutual TLS, access rules), with certificates made for the hub's address 10.203.0.1, which the
actors verify. Training must proceed with both actors' episodes arriving and both acting with
the learner's weights.

Needs root (CI runs as root) and iproute2; elsewhere the tests are skipped with the reason.
Namespaces (named per test run), links and processes are removed at the end, also on failure.
"""

from __future__ import annotations

import os
import secrets
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from common.certs import main as certs_main
from tests.processes import STOP_TIMEOUT_S, wait_for
from tests.zenoh_peer import PATH as PEER
from tests.zenoh_peer import read_lines

CONFIGS = Path(__file__).resolve().parents[1] / "deploy" / "configs"
SUBNET = "10.203.0"
HOSTS = {"hub": 1, "a1": 11, "a2": 12}  # host -> last octet
HUB = f"{SUBNET}.{HOSTS['hub']}"
SMOKE = ["--preset", "smoke", "--network.lstm_units", "16"]
DEADLINE_S = 75.0


class LabError(RuntimeError):
    pass


def ip(*args: str) -> None:
    result = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)
    if result.returncode != 0:
        raise LabError(f"`ip {' '.join(args)}` failed: {result.stderr.strip() or result.returncode}")


class Lab:
    """The namespaces of one test run and the processes started in them."""

    def __init__(self, directory: Path) -> None:
        tag = f"d3rqn-{os.getpid()}-{secrets.token_hex(3)}"
        self.namespaces = {name: f"{tag}-{name}" for name in (*HOSTS, "sw")}
        self.made: list[str] = []
        self.directory = directory
        self.processes: list[subprocess.Popen] = []
        self.logs: list[Path] = []

    def build(self) -> None:
        """The switch and three hosts; LabError names the command that failed."""
        for namespace in self.namespaces.values():
            ip("netns", "add", namespace)
            self.made.append(namespace)
        switch = self.namespaces["sw"]
        ip("-n", switch, "link", "add", "br0", "type", "bridge")
        ip("-n", switch, "link", "set", "br0", "up")
        for host, octet in HOSTS.items():
            namespace, port = self.namespaces[host], f"p-{host}"
            ip("-n", namespace, "link", "add", "eth0", "type", "veth", "peer", "name", port, "netns", switch)
            ip("-n", switch, "link", "set", port, "master", "br0", "up")
            ip("-n", namespace, "addr", "add", f"{SUBNET}.{octet}/24", "dev", "eth0")
            ip("-n", namespace, "link", "set", "eth0", "up")
            ip("-n", namespace, "link", "set", "lo", "up")

    def start(self, host: str, name: str, args: list[str]) -> subprocess.Popen:
        """`python <args>` inside host's namespace (ip netns exec execs it: the pid is python's)."""
        log = self.directory / f"{host}-{name}.log"
        self.logs.append(log)
        with open(log, "wb") as out:
            process = subprocess.Popen(["ip", "netns", "exec", self.namespaces[host], sys.executable, *args],
                                       stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                       cwd=self.directory)
        self.processes.append(process)
        return process

    def alive(self) -> None:
        dead = [log.name for process, log in zip(self.processes, self.logs) if process.poll() is not None]
        assert not dead, f"exited: {dead}\n{self.tails()}"

    def tails(self) -> str:
        return "\n".join(f"--- {log.name}\n{log.read_text(errors='replace')[-2500:]}" for log in self.logs
                         if log.exists())

    def teardown(self) -> None:
        """Stops the processes (SIGINT, then SIGKILL), kills anything still in a namespace, deletes them."""
        for process in self.processes:
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
        deadline = time.monotonic() + STOP_TIMEOUT_S
        for process in self.processes:
            try:
                process.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        leftovers = []
        for namespace in reversed(self.made):
            pids = subprocess.run(["ip", "netns", "pids", namespace], capture_output=True, text=True).stdout.split()
            for pid in pids:  # only this run's processes can be in its namespaces
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
            try:
                ip("netns", "del", namespace)  # takes its veth ends (and so their peers) and the bridge along
            except LabError as error:
                leftovers.append(str(error))
        listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
        leftovers += [namespace for namespace in self.made if namespace in listed.split()]
        if leftovers:
            raise AssertionError(f"namespaces left behind: {leftovers}")


def why_no_namespaces() -> str | None:
    if not sys.platform.startswith("linux"):
        return "network namespaces are Linux only"
    if os.geteuid() != 0:
        return "making network namespaces needs root (CI runs as root)"
    if shutil.which("ip") is None:
        return "the ip command (iproute2) is not installed"
    return None


@pytest.fixture
def lab(tmp_path):
    reason = why_no_namespaces()
    if reason:
        pytest.skip(reason)
    lab = Lab(tmp_path)
    try:
        try:
            lab.build()
        except LabError as error:
            pytest.skip(f"cannot make network namespaces and veth links here: {error}")
        yield lab
    finally:
        lab.teardown()


def config_flags(secure: bool, role: str) -> list[str]:
    """The deploy/configs file of a role, and the one flag docs/deployment.md adds for remote actors."""
    prefix = "secure-" if secure else ""
    name = {"replay": "hub-replay", "learner": "hub-learner", "actor": "remote-actor", "watch": "hub-learner"}[role]
    flags = ["--config", str(CONFIGS / f"{prefix}{name}.toml")]
    if role == "actor":
        flags += ["--transport.connect", f"{'tls' if secure else 'tcp'}/{HUB}:7447"]
    if role == "watch" and secure:  # a monitor on the hub, with the recorder's (an observer's) certificate
        flags += ["--transport.tls_certificate", "certs/recorder.pem", "--transport.tls_key", "certs/recorder-key.pem"]
    return flags


@pytest.mark.parametrize("secure", [False, True], ids=["tcp", "tls-mtls-acl"])
def test_actors_on_two_other_hosts_feed_the_hub(lab, secure):
    if secure:
        assert certs_main([str(lab.directory / "certs"), "--address", HUB]) == 0
    runs = ["--run.runs_dir", "runs"]
    lab.start("hub", "replay", ["-m", "replay.main", *config_flags(secure, "replay"), *SMOKE, *runs])
    watch = lab.directory / "watch.jsonl"
    lab.start("hub", "watch", [str(PEER), "watch", str(watch), *config_flags(secure, "watch")])
    wait_for(lambda: any(line["kind"] == "up" for line in read_lines(watch)), "the watcher's session", 30, lab.logs)
    lab.start("hub", "learner", ["-m", "learner.main", *config_flags(secure, "learner"), *SMOKE, *runs])
    for host, actor_id in (("a1", 1), ("a2", 2)):
        lab.start(host, "actor", ["-m", "actor.main", *config_flags(secure, "actor"), "--actor.actor_id", str(actor_id),
                                  *SMOKE])

    def trained() -> bool:
        lab.alive()
        lines = read_lines(watch)
        updates = max((line["updates"] or 0 for line in lines if line["kind"] == "learner"), default=0)
        episodes = [line for line in lines if line["kind"] == "episode"]
        arrived = {line["actor"] for line in episodes}
        learned = {line["actor"] for line in episodes if max(line["versions"]) >= 1}
        return updates >= 5 and arrived == learned == {1, 2}

    wait_for(trained, "5 updates, and episodes of actors 1 and 2 acted with the learner's weights", DEADLINE_S,
             lab.logs)
    lines = read_lines(watch)
    replay = [line for line in lines if line["kind"] == "replay"]
    assert replay and replay[-1]["inserted"] >= 2, replay[-1:]
    for host in ("a1", "a2"):  # the actors really were elsewhere: they dialled the hub's address over their link
        log = (lab.directory / f"{host}-actor.log").read_text()
        assert f"{HUB}:7447" in log, log[-2000:]
