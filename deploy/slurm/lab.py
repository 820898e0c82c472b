"""A Slurm cluster of one node on this machine, for trying the grid's batch script (tests/test_slurm_grid.py):
Debian's slurm-wlm and munge, installed where missing, and munged, slurmctld and slurmd run as root with a
key, a config, state, spool and logs of their own in one folder, on ports of their own, so that nothing of
the machine's (/etc/slurm, /etc/munge, a cluster it may belong to) is read or changed. The plugins need no
cgroups (proctrack/linuxproc, task/none): jobs are tracked by their process tree and limits are not
enforced. The node offers the CPUs the grid's tasks ask for, more than the machine has, so that a grid's
tasks run side by side as on several nodes.

`stop` ends the jobs, the daemons and every process left of them (found by this lab's SLURM_CONF in their
environment), then removes the folder.
"""

from __future__ import annotations

import os
import secrets
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path

PACKAGES = ("slurm-wlm", "munge")
TOOLS = ("munged", "slurmctld", "slurmd", "sbatch", "scontrol", "squeue")
APT_TIMEOUT_S = 600
UP_TIMEOUT_S = 60.0
JOBS_END_TIMEOUT_S = 90.0  # a cancelled job's processes get SIGTERM, then SIGKILL KillWait (30 s) later
CONFIG = """\
ClusterName=d3rqnlab
SlurmctldHost={host}(127.0.0.1)
SlurmctldPort={controller_port}
SlurmdPort={node_port}
SlurmUser=root
SlurmdUser=root
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={munge_socket}
StateSaveLocation={folder}/state
SlurmdSpoolDir={folder}/spool
SlurmctldPidFile={folder}/slurmctld.pid
SlurmdPidFile={folder}/slurmd.pid
SlurmctldLogFile={folder}/slurmctld.log
SlurmdLogFile={folder}/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
JobAcctGatherType=jobacct_gather/none
AccountingStorageType=accounting_storage/none
JobCompType=jobcomp/none
MailProg=/bin/true
MpiDefault=none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU_Memory
SchedulerType=sched/backfill
SlurmdParameters=config_overrides
ReturnToService=2
MinJobAge=3600
KillWait=30
SlurmctldDebug=error
SlurmdDebug=error
NodeName={host} NodeAddr=127.0.0.1 CPUs={cpus} RealMemory={memory_mb} State=UNKNOWN
PartitionName=lab Nodes={host} Default=YES MaxTime=INFINITE State=UP
"""


class SlurmLabError(RuntimeError):
    """The cluster cannot be installed or started here; the message says why."""


def why_no_slurm() -> str | None:
    """Why no cluster can be made here (None if it can)."""
    if os.geteuid() != 0:
        return "running slurmctld and slurmd as a cluster of this machine needs root (CI runs as root)"
    if all(shutil.which(tool) for tool in TOOLS):
        return None
    if shutil.which("apt-get") is None:
        return f"{', '.join(PACKAGES)} are not installed and there is no apt-get to install them"
    return None


def install() -> None:
    """Installs slurm-wlm and munge from Debian where their tools are missing (apt-get update first)."""
    if all(shutil.which(tool) for tool in TOOLS):
        return
    environment = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    for command in (["apt-get", "update", "-q"],
                    ["apt-get", "install", "-y", "-q", "--no-install-recommends", *PACKAGES]):
        done = subprocess.run(command, capture_output=True, text=True, env=environment, timeout=APT_TIMEOUT_S)
        if done.returncode != 0:
            raise SlurmLabError(f"{' '.join(command)} failed ({done.returncode}): {done.stderr.strip()[-500:]}")


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class SlurmLab:
    """munged, slurmctld and slurmd of one node, all under `folder`."""

    def __init__(self, folder: Path, cpus: int, memory_mb: int) -> None:
        self.folder = folder
        self.cpus, self.memory_mb = cpus, memory_mb
        self.conf = folder / "slurm.conf"
        self.munge_socket = folder / "munge" / "munge.socket"
        self.host = socket.gethostname().split(".")[0]

    @property
    def environment(self) -> dict[str, str]:
        """This process's environment with the lab's config: sbatch, squeue and scontrol talk to the lab."""
        return {**os.environ, "SLURM_CONF": str(self.conf)}

    def start(self) -> None:
        for name in ("state", "spool", "munge"):
            (self.folder / name).mkdir(parents=True, exist_ok=True, mode=0o700)
        key = self.folder / "munge" / "munge.key"
        key.write_bytes(secrets.token_bytes(128))
        key.chmod(0o400)
        munge = self.folder / "munge"
        self._daemon(["munged", "--force", f"--socket={self.munge_socket}", f"--key-file={key}",
                      f"--pid-file={munge}/munged.pid", f"--log-file={munge}/munged.log",
                      f"--seed-file={munge}/munged.seed"])
        self.conf.write_text(CONFIG.format(host=self.host, controller_port=free_port(), node_port=free_port(),
                                           munge_socket=self.munge_socket, folder=self.folder, cpus=self.cpus,
                                           memory_mb=self.memory_mb))
        self._daemon(["slurmctld", "-i"])
        self._daemon(["slurmd"])
        self._wait_idle()

    def _daemon(self, command: list[str]) -> None:
        done = subprocess.run(command, capture_output=True, text=True, env=self.environment, timeout=60)
        if done.returncode != 0:
            raise SlurmLabError(f"{command[0]} did not start ({done.returncode}): {done.stderr.strip()}; "
                                f"logs in {self.folder}")

    def _wait_idle(self) -> None:
        deadline = time.monotonic() + UP_TIMEOUT_S
        state = ""
        while time.monotonic() < deadline:
            state = self.run("sinfo", "-h", "-N", "-o", "%T", check=False).strip()
            if state == "idle":
                return
            time.sleep(1.0)
        raise SlurmLabError(f"the node is {state or 'not reported'} after {UP_TIMEOUT_S:.0f} s, not idle; "
                            f"logs in {self.folder}")

    def run(self, *command: str, check: bool = True) -> str:
        """A Slurm command against the lab; its stdout."""
        done = subprocess.run(command, capture_output=True, text=True, env=self.environment, timeout=60)
        if check and done.returncode != 0:
            raise SlurmLabError(f"{' '.join(command)} failed ({done.returncode}): {done.stderr.strip()}")
        return done.stdout

    def job(self, job_id: str) -> dict[str, str]:
        """scontrol's fields of a job (an array's task as <job>_<task>), kept MinJobAge after it ends."""
        fields = self.run("scontrol", "show", "job", "-o", job_id).split()
        return dict(field.split("=", 1) for field in fields if "=" in field)

    def queued(self) -> list[str]:
        """The jobs pending or running, as <job> or <array job>_<task>."""
        return self.run("squeue", "-h", "-o", "%i", check=False).split()

    def stop(self) -> None:
        """Cancels the jobs, stops the daemons and whatever is left of them, removes the folder."""
        if self.conf.is_file():
            self.run("scancel", "--full", "--user", "root", check=False)
            deadline = time.monotonic() + JOBS_END_TIMEOUT_S
            while self.queued() and time.monotonic() < deadline:
                time.sleep(1.0)
            for name in ("slurmd", "slurmctld"):
                self._end(self.folder / f"{name}.pid")
        self._end(self.folder / "munge" / "munged.pid")
        for pid in self._left():
            _signal(pid, signal.SIGKILL)
        shutil.rmtree(self.folder, ignore_errors=True)

    def _end(self, pid_file: Path) -> None:
        try:
            pid = int(pid_file.read_text().strip())
        except (OSError, ValueError):
            return
        _signal(pid, signal.SIGTERM)
        deadline = time.monotonic() + 15.0
        while _running(pid) and time.monotonic() < deadline:
            time.sleep(0.2)
        _signal(pid, signal.SIGKILL)

    def _left(self) -> list[int]:
        """Processes of this lab's jobs still running (slurmstepd and what it started): SLURM_CONF is in their
        environment, as sbatch passed it on."""
        mark = f"SLURM_CONF={self.conf}".encode()
        left = []
        for entry in Path("/proc").iterdir():
            if entry.name.isdigit() and int(entry.name) != os.getpid():
                try:
                    if mark in (entry / "environ").read_bytes().split(b"\0"):
                        left.append(int(entry.name))
                except OSError:
                    continue
        return left


def _signal(pid: int, signum: int) -> None:
    try:
        os.kill(pid, signum)
    except ProcessLookupError:
        pass


def _running(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().split(") ", 1)[1][0] != "Z"
    except OSError:
        return False
