"""The learner's checkpoint: one file of named sections, written atomically, read back by name.

The learner writes it (<run>/checkpoints/latest.pt, common/run_dir.py) and reads
it on --resume; evaluate takes the greedy policy from it, the grid runner how
far a run got. Only this module knows what the file holds:

    learner      DoubleQLearner.state_dict(): online, target, optimizer, updates
    exploration  the strategy's state_dict()
    clock        RunClock.state_dict(): env_steps (of the whole system), start_env_steps, wall_s
    config       the run's config as a table (common.config_values.to_dict)

The policies the learner keeps for greedy learning curves (learner.keep_every,
<run>/policies/) are files of their own, KeptPolicy: one network's weights, of a kind (the online
network; beyond the paper, the target network or the learner's moving average beside it).
A policy shipped with the project (deploy/tools/ship_policy.py) is a KeptPolicy too,
its weights in 16 bits (POLICY_ENCODINGS), half the size; reading it widens
them to float32. So is the mean of several kept policies' weights
(deploy/tools/average_policies.py), which names the updates of those it averaged.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from common import atomic_file
from common.run_dir import CHECKPOINT_FILE, POLICY_KINDS, find_checkpoint

SECTIONS = ("learner", "exploration", "clock", "config")


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable or not one of ours."""


class Checkpoint:
    """The sections of a checkpoint; reading one it does not hold is a CheckpointError naming the file."""

    def __init__(self, learner: dict | None = None, exploration: dict | None = None, clock: dict | None = None,
                 config: dict | None = None, path: Path | None = None) -> None:
        given = {"learner": learner, "exploration": exploration, "clock": clock, "config": config}
        self._sections = {name: section for name, section in given.items() if section is not None}
        self.path = path  # the file it was read from

    @classmethod
    def load(cls, path: Path, complete: bool = False) -> Checkpoint:
        """A checkpoint file, a run folder or its checkpoints folder; complete: every section must be there."""
        file = _locate(path)
        return cls._of(_read(file, SECTIONS if complete else ()), file)

    @classmethod
    def _of(cls, payload: dict[str, Any], file: Path) -> Checkpoint:
        return cls(**{name: payload.get(name) for name in SECTIONS}, path=file)

    def save(self, directory: Path) -> Path:
        return save_checkpoint(directory, self._sections)

    def _section(self, name: str) -> dict:
        section = self._sections.get(name)
        if not isinstance(section, dict):
            state = "lacks its" if section is None else "has a malformed"
            raise CheckpointError(f"checkpoint {self.path} {state} {name} section")
        return section

    @property
    def learner(self) -> dict:
        return self._section("learner")

    @property
    def exploration(self) -> dict:
        return self._section("exploration")

    @property
    def clock(self) -> dict:
        return self._section("clock")

    @property
    def config(self) -> dict:
        return self._section("config")

    @property
    def env_steps(self) -> int | None:
        """The env steps of the whole system when it was saved; None if the checkpoint does not say."""
        return self._count("clock", "env_steps")

    @property
    def updates(self) -> int | None:
        """The learner's updates when it was saved; None if the checkpoint does not say."""
        return self._count("learner", "updates")

    def policy_weights(self) -> dict[str, np.ndarray]:
        """The online network's tensors, the greedy policy, as numpy arrays by parameter name."""
        online = self.learner.get("online")
        if not isinstance(online, dict):
            raise CheckpointError(f"checkpoint {self.path} has no online network in its learner section")
        return _numpy(online)

    def _count(self, section: str, name: str) -> int | None:
        if section not in self._sections or name not in self._section(section):
            return None
        value = self._section(section)[name]
        if not _is_count(value):
            raise CheckpointError(f"checkpoint {self.path}: {section} {name} {value!r} is not a count")
        return value


POLICY_FORMAT = "d3rqn kept policy"  # a kept policy's "format" entry: tells it from a checkpoint or a stranger
# how a policy file may hold its weights: as trained (the learner's), or in 16 bits (a shipped policy)
POLICY_ENCODINGS = {"float32": torch.float32, "float16": torch.float16, "bfloat16": torch.bfloat16}
TRAINED_PRECISIONS = ("", "float32", "bfloat16")  # a kept policy's learner precision; "": not recorded


@dataclass(frozen=True)
class KeptPolicy:
    """A policy the learner kept: the online weights and where the run stood when it kept them.

    The file is one dict: format (POLICY_FORMAT) and the fields below but path. The learner keeps the
    weights in float32; compact() narrows them to one of the 16-bit POLICY_ENCODINGS, and weights()
    widens them back to float32 on any CPU.
    """

    updates: int
    env_steps: int  # of the whole system
    wall_s: float  # since the run started, summed over the learner's sessions of a resumed run
    cpu: str  # the learner host's CPU model: wall_s is that machine's time
    config: dict  # the run's config as a table (common.config_values.to_dict): it rebuilds the network
    online: dict[str, torch.Tensor]  # the online network's state dict
    averaged: tuple[int, ...] = ()  # the updates of the kept policies whose mean these weights are; () if none
    # the learner's update precision when it kept them (learner.precision auto differs by CPU); "" if unrecorded
    precision: str = ""
    kind: str = "online"  # which weights: POLICY_KINDS (common/run_dir.py); a file without the field is online
    path: Path | None = None  # the file it was read from

    def save(self, path: Path) -> Path:
        fields = {name: getattr(self, name) for name in _POLICY_CHECKS}
        mean = {"averaged": list(self.averaged)} if self.averaged else {}  # a learner's file stays as it was
        precision = {"precision": self.precision} if self.precision else {}
        write_atomically(path, {"format": POLICY_FORMAT, **fields, **mean, **precision, "kind": self.kind})
        return path

    @classmethod
    def load(cls, path: Path) -> KeptPolicy:
        """The kept policy in a file; a CheckpointError naming the file if it is damaged or not one."""
        payload = _read(path, (), "kept policy")
        if payload.get("format") != POLICY_FORMAT:
            raise CheckpointError(f"{path} is not a kept policy (a learner checkpoint? `evaluate --checkpoint` "
                                  "reads those)")
        return cls._of(payload, path)

    @classmethod
    def _of(cls, payload: dict[str, Any], path: Path, kind: str = "kept policy") -> KeptPolicy:
        wrong = [name for name, check in _POLICY_CHECKS.items() if not check(payload.get(name))]
        averaged = payload.get("averaged", [])
        if not (isinstance(averaged, (list, tuple)) and all(_is_count(updates) for updates in averaged)):
            wrong.append("averaged")
        precision = payload.get("precision", "")  # absent in a policy kept before the learner recorded it
        if precision not in TRAINED_PRECISIONS:
            wrong.append("precision")
        weights = payload.get("kind", "online")  # absent in a policy kept before the kinds
        if weights not in POLICY_KINDS:
            wrong.append("kind")
        if wrong:
            raise CheckpointError(f"{kind} {path}: {', '.join(wrong)} missing or malformed")
        return cls(**{name: payload[name] for name in _POLICY_CHECKS}, averaged=tuple(averaged), precision=precision,
                   kind=weights, path=path)

    @classmethod
    def of_checkpoint(cls, checkpoint: Checkpoint) -> KeptPolicy:
        """The greedy policy of a learner checkpoint, with its updates, env steps and wall time; a checkpoint
        does not name the learner's CPU ("unknown")."""
        fields = {"updates": checkpoint.updates, "env_steps": checkpoint.env_steps,
                  "wall_s": checkpoint.clock.get("wall_s", 0.0),  # 0: a checkpoint from before the clock kept it
                  "cpu": "unknown", "config": checkpoint.config, "online": checkpoint.learner.get("online")}
        return cls._of(fields, checkpoint.path, "checkpoint")

    @property
    def encoding(self) -> str:
        """How the file holds the weights: float32 (as trained) or a 16-bit encoding (shipped); "mixed" for
        weights of several dtypes, which no file read back holds."""
        return next((name for name, dtype in POLICY_ENCODINGS.items() if dtype == _dtype(self.online)), "mixed")

    def compact(self, encoding: str) -> KeptPolicy:
        """The same policy with its weights rounded to a 16-bit encoding (to nearest, ties to even). A weight
        beyond the encoding's range is a CheckpointError that names it: float16's is +-65,504 (bfloat16's
        is float32's); so is a NaN or an infinity."""
        dtype = POLICY_ENCODINGS.get(encoding)
        if dtype is None or dtype == torch.float32:
            raise CheckpointError(f"a compact policy is {' or '.join(_COMPACT)}, not {encoding!r}")
        online = {}
        for name, tensor in self.online.items():
            wide = tensor.detach().cpu().float()
            if not torch.isfinite(wide).all():
                raise CheckpointError(f"weights {name!r} hold NaN or infinity")
            online[name] = wide.to(dtype)
            if not torch.isfinite(online[name]).all():
                raise CheckpointError(f"weights {name!r}: a magnitude of {wide.abs().max().item():.6g} is beyond "
                                      f"{encoding}'s {torch.finfo(dtype).max:.6g}; bfloat16 has float32's range")
        return dataclasses.replace(self, online=online, path=None)

    def weights(self) -> dict[str, np.ndarray]:
        """The online network's tensors as float32 numpy arrays by parameter name, as evaluate takes them."""
        return _numpy(self.online)


def _is_count(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


_POLICY_CHECKS = {
    "updates": _is_count,
    "env_steps": _is_count,
    "wall_s": lambda value: isinstance(value, (int, float)) and not isinstance(value, bool)
    and math.isfinite(value) and value >= 0,
    "cpu": lambda value: isinstance(value, str),
    "config": lambda value: isinstance(value, dict),
    "online": lambda value: isinstance(value, dict) and bool(value)
    and all(isinstance(tensor, torch.Tensor) for tensor in value.values()) and _dtype(value) is not None,
}
_COMPACT = [name for name, dtype in POLICY_ENCODINGS.items() if dtype != torch.float32]


def _dtype(tensors: dict[str, torch.Tensor]) -> torch.dtype | None:
    """The one dtype of POLICY_ENCODINGS all the tensors have; None for a mix or another."""
    dtypes = {tensor.dtype for tensor in tensors.values()}
    return dtypes.pop() if len(dtypes) == 1 and next(iter(dtypes)) in POLICY_ENCODINGS.values() else None


def _numpy(tensors: dict) -> dict[str, np.ndarray]:
    """float32 numpy arrays; 16-bit floats are widened exactly (numpy has no bfloat16)."""
    return {name: tensor.detach().cpu().float().numpy() for name, tensor in tensors.items()}


def save_checkpoint(directory: Path, payload: dict[str, Any]) -> Path:
    """The checkpoint's sections into <directory>/latest.pt, replacing the old one whole."""
    return write_atomically(directory / CHECKPOINT_FILE, payload)


def write_atomically(path: Path, payload: dict[str, Any]) -> Path:
    """Writes to a temporary file, then renames it over `path`: a crash leaves the old file or the new one, a
    failure no part. Through a handle, so that a full disk's OSError is the cause of torch's RuntimeError."""
    return atomic_file.write_atomically(path, lambda handle: torch.save(payload, handle))


def load_checkpoint(path: Path, required: tuple[str, ...] = ()) -> dict[str, Any]:
    """The sections of a checkpoint (a file, a run folder or its checkpoints folder), checked for `required`."""
    return _read(_locate(path), required)


def load_checkpoint_or_policy(path: Path) -> Checkpoint | KeptPolicy:
    """What a path holds, read once: a kept (or shipped) policy file, or a learner checkpoint (a file, a run
    folder or its checkpoints folder). A damaged file, or one of neither kind, is a CheckpointError."""
    file = _locate(path)
    payload = _read(file, (), "checkpoint or policy")
    return KeptPolicy._of(payload, file) if payload.get("format") == POLICY_FORMAT else Checkpoint._of(payload, file)


def _locate(path: Path) -> Path:
    file = find_checkpoint(path)
    if file is None:
        raise CheckpointError(f"no checkpoint at {path} (expected a checkpoint file, a run folder or "
                              f"a folder with {CHECKPOINT_FILE})")
    return file


def _read(file: Path, required: tuple[str, ...], kind: str = "checkpoint") -> dict[str, Any]:
    try:
        payload = torch.load(file, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for a damaged file
        raise CheckpointError(f"cannot read {kind} {file} (damaged, cut short or not a torch file): "
                              f"{error}") from None
    if not isinstance(payload, dict):
        raise CheckpointError(f"{kind} {file} is not a d3rqn {kind}")
    missing = [name for name in required if name not in payload]
    if missing:
        raise CheckpointError(f"{kind} {file} lacks {', '.join(missing)}")
    return payload
