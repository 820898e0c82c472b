"""The learner's checkpoint: one file of named sections, written atomically, read back by name.

The learner writes it (<run>/checkpoints/latest.pt, common/run_dir.py) and reads
it on --resume; evaluate takes the greedy policy from it, the grid runner how
far a run got. Only this module knows what the file holds:

    learner      DoubleQLearner.state_dict(): online, target, optimizer, updates
    exploration  the strategy's state_dict()
    clock        RunClock.state_dict(): env_steps (of the whole system), start_env_steps
    config       the run's config as a table (common.config.to_dict)
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from common.run_dir import CHECKPOINT_FILE, find_checkpoint

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
        payload = _read(file, SECTIONS if complete else ())
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
        return {name: tensor.detach().cpu().numpy() for name, tensor in online.items()}

    def _count(self, section: str, name: str) -> int | None:
        if section not in self._sections or name not in self._section(section):
            return None
        value = self._section(section)[name]
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise CheckpointError(f"checkpoint {self.path}: {section} {name} {value!r} is not a count")
        return value


def save_checkpoint(directory: Path, payload: dict[str, Any]) -> Path:
    """Writes to a temporary file, then renames it over the old checkpoint: a crash leaves one whole file."""
    directory.mkdir(parents=True, exist_ok=True)
    final = directory / CHECKPOINT_FILE
    temporary = directory / f".{CHECKPOINT_FILE}.{os.getpid()}.tmp"
    torch.save(payload, temporary)
    with open(temporary, "rb") as handle:
        os.fsync(handle.fileno())
    os.replace(temporary, final)
    return final


def load_checkpoint(path: Path, required: tuple[str, ...] = ()) -> dict[str, Any]:
    """The sections of a checkpoint (a file, a run folder or its checkpoints folder), checked for `required`."""
    return _read(_locate(path), required)


def _locate(path: Path) -> Path:
    file = find_checkpoint(path)
    if file is None:
        raise CheckpointError(f"no checkpoint at {path} (expected a checkpoint file, a run folder or "
                              f"a folder with {CHECKPOINT_FILE})")
    return file


def _read(file: Path, required: tuple[str, ...]) -> dict[str, Any]:
    try:
        payload = torch.load(file, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for a damaged file
        raise CheckpointError(f"cannot read checkpoint {file}: {error}") from None
    if not isinstance(payload, dict):
        raise CheckpointError(f"checkpoint {file} is not a d3rqn checkpoint")
    missing = [name for name in required if name not in payload]
    if missing:
        raise CheckpointError(f"checkpoint {file} lacks {', '.join(missing)}")
    return payload
