"""The run folder, <run.runs_dir>/<run.name>/: every path of a run, and the stack's status file.

    config.toml                 the config the stack started the run with
    logs/<process>.log          one file per process of the stack; the grid adds stack.log, evaluate.log
    checkpoints/latest.pt       the learner's checkpoint (common/checkpoint.py)
    policies/policy-u<updates>.pt  the policies the learner kept (learner.keep_every), 7-digit updates
    policies/<kind>/policy-u<updates>.pt  the same of another kind (POLICY_KINDS): target, ema, mean
    curve/                      `evaluate --curve`'s greedy learning curve of the kept policies
    replay/rate_limiter.json    the replay's counters, and replay/snapshot/ its episodes (replay --resume)
    traffic.mcap                the flight recorder's log; traffic-2.mcap, ... after each restart
    evaluation/                 evaluate's report
    status.json                 what the stack is doing, rewritten while it runs (RunStatus)
    soak/                       deploy/labs/soak.py's samples of memory, folder size and restarts
    summary.json                the stack's figures of the whole run, written when it stops
    abandoned/<time>/           what an attempt that never checkpointed left behind (the grid runner)

No other module spells these names: each asks a RunDir.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

from common.atomic_file import pid_alive as _alive, write_text_atomically

CHECKPOINTS = "checkpoints"
CHECKPOINT_FILE = "latest.pt"
POLICIES = "policies"
POLICY_FILE = re.compile(r"policy-u(\d+)\.pt")
# what a kept policy's weights are: the online network (the policy the actors act by), the learner's target
# network and its moving average of the online weights (learner.keep_target, learner.ema_updates), and the
# mean of a run's last kept online policies (deploy/tools/average_policies.py); all but online are beyond the paper
POLICY_KINDS = ("online", "target", "ema", "mean")


class StatusError(ValueError):
    """A status file that cannot be read as one."""


@dataclass(frozen=True)
class RunDir:
    root: Path

    @classmethod
    def of(cls, config) -> RunDir:
        """The folder of the run a config describes (run.runs_dir, run.name)."""
        return cls(Path(config.run.runs_dir) / config.run.name)

    @classmethod
    def of_checkpoint(cls, checkpoint: Path) -> RunDir:
        """The run a checkpoint or kept policy file belongs to: <run>/checkpoints/latest.pt or
        <run>/policies/policy-u<updates>.pt, else the folder it lies in."""
        folder = checkpoint.parent
        if folder.parent.name == POLICIES and folder.name in POLICY_KINDS:
            return cls(folder.parent.parent)
        return cls(folder.parent if folder.name in (CHECKPOINTS, POLICIES) else folder)

    @property
    def config(self) -> Path:
        return self.root / "config.toml"

    @property
    def logs(self) -> Path:
        return self.root / "logs"

    def log(self, process: str) -> Path:
        return self.logs / f"{process}.log"

    @property
    def checkpoints(self) -> Path:
        return self.root / CHECKPOINTS

    @property
    def checkpoint(self) -> Path:
        return self.checkpoints / CHECKPOINT_FILE

    @property
    def policies(self) -> Path:
        return self.root / POLICIES

    def policy(self, updates: int, kind: str = "online") -> Path:
        """The kept policy of this many updates and kind; zero-padded, so the names sort by updates."""
        return self.policy_folder(kind) / f"policy-u{updates:07d}.pt"

    def policy_folder(self, kind: str = "online") -> Path:
        if kind not in POLICY_KINDS:
            raise ValueError(f"a policy kind is one of {', '.join(POLICY_KINDS)}, not {kind!r}")
        return self.policies if kind == "online" else self.policies / kind

    def kept_policies(self, kind: str = "online") -> list[tuple[int, Path]]:
        """(updates, file) of every kept policy of a kind, by updates."""
        found = [(int(match[1]), path) for path in self.policy_folder(kind).glob("policy-u*.pt")
                 if (match := POLICY_FILE.fullmatch(path.name))]
        return sorted(found)

    def evaluation_of(self, kind: str = "online") -> Path:
        """evaluate's report of a run's chosen policy of a kind: evaluation/, or evaluation-<kind>/."""
        self.policy_folder(kind)  # a known kind
        return self.evaluation if kind == "online" else self.root / f"evaluation-{kind}"

    @property
    def curve(self) -> Path:
        return self.root / "curve"

    @property
    def replay_counters(self) -> Path:
        return self.root / "replay" / "rate_limiter.json"

    @property
    def replay_snapshot(self) -> Path:
        return self.root / "replay" / "snapshot"

    @property
    def wire_log(self) -> Path:
        """The first recorder's log of the run's messages (named traffic.mcap, as every run folder has it); the
        next recorders of the run write numbered ones (next_free_path)."""
        return self.root / "traffic.mcap"

    def wire_log_segments(self) -> list[Path]:
        return log_segments(self.wire_log)

    @property
    def evaluation(self) -> Path:
        return self.root / "evaluation"

    @property
    def tensorboard(self) -> Path:
        """The recorder's live TensorBoard event files (deploy/launcher/stack.py --tensorboard)."""
        return self.root / "tensorboard"

    @property
    def status(self) -> Path:
        return self.root / "status.json"

    @property
    def summary(self) -> Path:
        return self.root / "summary.json"

    @property
    def stack_lock(self) -> Path:
        """Locked (flock) by the stack that runs the run: one at a time (deploy/launcher/run_claim.py)."""
        return self.root / ".stack.lock"

    @property
    def soak(self) -> Path:
        return self.root / "soak"

    def abandoned(self, stamp: str) -> Path:
        return self.root / "abandoned" / stamp


def find_checkpoint(path: Path) -> Path | None:
    """The checkpoint file a path names: the file itself, or latest.pt in a run folder's checkpoints/
    or in the folder given; None if there is none."""
    if path.is_file():
        return path
    for candidate in (RunDir(path).checkpoint, path / CHECKPOINT_FILE):
        if candidate.is_file():
            return candidate
    return None


# --- numbered files: a recorder never overwrites a log ---------------------------------------------------

def numbered_paths(path: Path) -> Iterator[Path]:
    """path, then path with -2, -3, ... before its suffix."""
    yield path
    for number in itertools.count(2):
        yield path.with_name(f"{path.stem}-{number}{path.suffix}")


def next_free_path(path: Path) -> Path:
    """The first of numbered_paths(path) that does not exist."""
    return next(candidate for candidate in numbered_paths(path) if not candidate.exists())


def log_segments(path: Path) -> list[Path]:
    """The files next_free_path gave the recorders of one run (a resumed run has several), in recording order."""
    return list(itertools.takewhile(Path.exists, numbered_paths(path)))


# --- the status file ---------------------------------------------------------------------------------------

@dataclass
class RunStatus:
    """What the local stack is doing; it rewrites <run>/status.json with it while it runs."""

    phase: str  # "training" while the processes run, then "stopping", then "finished" or "stopped"
    env_steps: int = 0  # of the whole system, as the replay counts them
    total_env_steps: int = 0  # the budget, pace.total_env_steps
    updates: int = 0
    episodes: int = 0  # episodes finished while this stack watched
    mean_return: float | None = None  # of the last 100 of those; None before the first
    eta_s: float | None = None  # seconds to the budget at the recent rate; None while unknown
    elapsed_s: float = 0.0  # since this stack started
    restarts: dict[str, int] = field(default_factory=dict)  # process -> times it was started again
    pids: dict[str, int] = field(default_factory=dict)  # process -> its pid now
    disk_free_bytes: int | None = None  # free on the run folder's disk; None where unknown
    time: float = 0.0  # wall clock (time.time()) when written

    def write(self, path: Path) -> None:
        """Atomically: a reader sees the previous status or this one, never a part."""
        write_text_atomically(path, json.dumps(dataclasses.asdict(self), indent=2) + "\n")

    def training(self) -> bool:
        """Whether the stack still trains: its phase says so and one of its processes lives (a stack killed
        outright leaves "training" behind). The pids are this machine's."""
        return self.phase == "training" and any(_alive(pid) for pid in self.pids.values())

    @classmethod
    def read(cls, path: Path) -> RunStatus:
        try:
            values = json.loads(path.read_text())
        except (OSError, ValueError) as error:
            raise StatusError(f"cannot read the status file {path}: {error}") from None
        names = {item.name for item in dataclasses.fields(cls)}
        if not isinstance(values, dict) or "phase" not in values or set(values) - names:
            raise StatusError(f"{path} is not a run status file")
        wrong = [name for name, value in values.items() if not _fits(name, value)]
        if wrong:
            raise StatusError(f"{path}: {', '.join(wrong)} of the wrong type")
        return cls(**values)


def _fits(name: str, value) -> bool:
    """Whether a value read from a status file has its field's type."""
    def count(item) -> bool:
        return isinstance(item, int) and not isinstance(item, bool)

    def number(item) -> bool:
        return isinstance(item, (int, float)) and not isinstance(item, bool)

    if name == "phase":
        return isinstance(value, str)
    if name in ("restarts", "pids"):
        return isinstance(value, dict) and all(isinstance(key, str) and count(item) for key, item in value.items())
    if name in ("mean_return", "eta_s"):
        return value is None or number(value)
    if name == "disk_free_bytes":
        return value is None or count(value)
    if name in ("elapsed_s", "time"):
        return number(value)
    return count(value)
