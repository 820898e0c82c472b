"""A lab of hosts as Linux network namespaces on one switch, and the network faults it can put on a
host's link: docs/deployment.md "Across machines" for real, for the tests and the benchmarks.

    hub  10.203.0.1   replay (router) + learner, from deploy/configs/hub-replay.toml and hub-learner.toml
    a1   10.203.0.11  actor 1, from remote-actor.toml with --transport.connect tcp/10.203.0.1:7447
    a2   10.203.0.12  actor 2, the same (more actor hosts: a3, a4, ...)
    sw                a bridge; each host's eth0 is one end of a veth pair whose other end is a port of it

Each host has only its loopback and its eth0, so an actor reaches the hub over its veth link and
the bridge, as it would over a LAN. The faults, on one host's link, both ways:

- partition: nftables drops every packet on the host's eth0 (silently, as a dead switch port);
- loss: nftables drops a share of them at random (``numgen random``; this kernel has no netem);
- cap: ``tc tbf`` limits the rate on the host's eth0 and on its switch port.

Needs root and iproute2 (nftables for partition and loss); `why_no_lab` says what is missing.
Namespaces are named per lab, and `teardown` removes them with everything running in them.
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

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
SUBNET = "10.203.0"
HUB = f"{SUBNET}.1"
PORT = 7447
STOP_TIMEOUT_S = 30.0
FAULT_TABLE = "d3rqn_fault"


class LabError(RuntimeError):
    pass


def run(*command: str, stdin: str | None = None) -> None:
    """Runs a command; LabError names it if it fails."""
    result = subprocess.run(command, capture_output=True, text=True, timeout=30, input=stdin)
    if result.returncode != 0:
        raise LabError(f"`{' '.join(command)}` failed: {result.stderr.strip() or result.returncode}")


def ip(*args: str) -> None:
    run("ip", *args)


def why_no_lab(faults: bool = False) -> str | None:
    """Why a lab cannot be made here (None if it can); with faults, nftables and tc are needed too."""
    if not sys.platform.startswith("linux"):
        return "network namespaces are Linux only"
    if os.geteuid() != 0:
        return "making network namespaces needs root (CI runs as root)"
    needed = ("ip", "nft", "tc") if faults else ("ip",)
    missing = [tool for tool in needed if shutil.which(tool) is None]
    if missing:
        return (f"{', '.join(missing)} not installed (iproute2, nftables: "
                f"deploy/test.sh installs them on Debian as root)")
    return None


def host_address(host: str) -> str:
    """hub -> .1, aN -> .1N (a1 .11, a2 .12, ...)."""
    return HUB if host == "hub" else f"{SUBNET}.{10 + int(host[1:])}"


class Lab:
    """The namespaces of one lab and the processes started in them."""

    def __init__(self, directory: Path, actor_hosts: int = 2) -> None:
        tag = f"d3rqn-{os.getpid()}-{secrets.token_hex(3)}"
        self.hosts = ["hub", *(f"a{n}" for n in range(1, actor_hosts + 1))]
        self.namespaces = {name: f"{tag}-{name}" for name in (*self.hosts, "sw")}
        self.made: list[str] = []
        self.directory = directory
        self.processes: dict[subprocess.Popen, Path] = {}  # the running ones, with their logs
        self.logs: list[Path] = []

    def build(self) -> None:
        """The switch and the hosts; LabError names the command that failed."""
        for namespace in self.namespaces.values():
            ip("netns", "add", namespace)
            self.made.append(namespace)
        switch = self.namespaces["sw"]
        ip("-n", switch, "link", "add", "br0", "type", "bridge")
        ip("-n", switch, "link", "set", "br0", "up")
        for host in self.hosts:
            namespace, port = self.namespaces[host], f"p-{host}"
            ip("-n", namespace, "link", "add", "eth0", "type", "veth", "peer", "name", port, "netns", switch)
            ip("-n", switch, "link", "set", port, "master", "br0", "up")
            ip("-n", namespace, "addr", "add", f"{host_address(host)}/24", "dev", "eth0")
            ip("-n", namespace, "link", "set", "eth0", "up")
            ip("-n", namespace, "link", "set", "lo", "up")

    def start(self, host: str, name: str, args: list[str]) -> subprocess.Popen:
        """`python <args>` inside host's namespace (ip netns exec execs it: the pid is python's)."""
        log = self.directory / f"{host}-{name}.log"
        if log not in self.logs:
            self.logs.append(log)
        with open(log, "ab") as out:
            process = subprocess.Popen(["ip", "netns", "exec", self.namespaces[host], sys.executable, *args],
                                       stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                       cwd=self.directory)
        self.processes[process] = log
        return process

    def alive(self) -> None:
        """AssertionError naming the processes that exited (a stopped one is taken out of the list first)."""
        dead = [log.name for process, log in self.processes.items() if process.poll() is not None]
        assert not dead, f"exited: {dead}\n{self.tails()}"

    def forget(self, process: subprocess.Popen) -> None:
        """A process stopped on purpose: no longer watched by `alive`."""
        self.processes.pop(process, None)

    def tails(self, chars: int = 2500) -> str:
        return "\n".join(f"--- {log.name}\n{log.read_text(errors='replace')[-chars:]}" for log in self.logs
                         if log.exists())

    # --- faults on one host's link -----------------------------------------------------

    def partition(self, host: str) -> None:
        self._drop(host, "drop")

    def loss(self, host: str, percent: int) -> None:
        self._drop(host, f"numgen random mod 100 < {percent} drop")

    def _drop(self, host: str, verdict: str) -> None:
        self.heal(host)
        rules = (f"table inet {FAULT_TABLE} {{\n"
                 f"  chain in {{ type filter hook input priority 0; policy accept; iifname \"eth0\" {verdict}; }}\n"
                 f"  chain out {{ type filter hook output priority 0; policy accept; oifname \"eth0\" {verdict}; }}\n"
                 f"}}\n")
        run("ip", "netns", "exec", self.namespaces[host], "nft", "-f", "-", stdin=rules)

    def cap(self, host: str, mbit: float) -> None:
        """tbf at mbit both ways: on the host's eth0 (what it sends) and its switch port (what it receives)."""
        self.heal(host)
        for namespace, device in ((self.namespaces[host], "eth0"), (self.namespaces["sw"], f"p-{host}")):
            run("tc", "-n", namespace, "qdisc", "add", "dev", device, "root", "tbf", "rate", f"{mbit}mbit",
                "burst", "64kb", "latency", "500ms")

    def heal(self, host: str) -> None:
        """Takes every fault off the host's link (nothing to take off is fine)."""
        subprocess.run(["ip", "netns", "exec", self.namespaces[host], "nft", "delete", "table", "inet", FAULT_TABLE],
                       capture_output=True, timeout=30)
        for namespace, device in ((self.namespaces[host], "eth0"), (self.namespaces["sw"], f"p-{host}")):
            subprocess.run(["tc", "-n", namespace, "qdisc", "del", "dev", device, "root"], capture_output=True,
                           timeout=30)

    # --- the end -------------------------------------------------------------------------

    def stop(self, process: subprocess.Popen, sig: int = signal.SIGINT) -> int:
        """Stops one process (killed if it does not stop in time) and forgets it; its exit code."""
        if process.poll() is None:
            process.send_signal(sig)
        try:
            code = process.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            process.kill()
            code = process.wait()
        self.forget(process)
        return code

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
            for pid in pids:  # only this lab's processes can be in its namespaces
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


def config_flags(secure: bool, role: str) -> list[str]:
    """The deploy/configs file of a role, and the one flag docs/deployment.md adds for remote actors."""
    prefix = "secure-" if secure else ""
    name = {"replay": "hub-replay", "learner": "hub-learner", "actor": "remote-actor", "watch": "hub-learner"}[role]
    flags = ["--config", str(CONFIGS / f"{prefix}{name}.toml")]
    if role == "actor":
        flags += ["--transport.connect", f"{'tls' if secure else 'tcp'}/{HUB}:{PORT}"]
    if role == "watch" and secure:  # a monitor on the hub, with the recorder's (an observer's) certificate
        flags += ["--transport.tls_certificate", "certs/recorder.pem", "--transport.tls_key", "certs/recorder-key.pem"]
    return flags
