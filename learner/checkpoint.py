"""Atomic checkpoints: write to a temporary file, then rename over the old one."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

LATEST = "latest.pt"


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable or not one of ours."""


def save_checkpoint(directory: Path, payload: dict[str, Any]) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    final = directory / LATEST
    temporary = directory / f".{LATEST}.{os.getpid()}.tmp"
    torch.save(payload, temporary)
    with open(temporary, "rb") as handle:
        os.fsync(handle.fileno())
    os.replace(temporary, final)
    return final


def load_checkpoint(path: Path, required: tuple[str, ...]) -> dict[str, Any]:
    """Loads a checkpoint file (or the latest in a directory) and checks its sections."""
    path = path / LATEST if path.is_dir() else path
    if not path.exists():
        raise CheckpointError(f"no checkpoint at {path}")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch raises many types for a damaged file
        raise CheckpointError(f"cannot read checkpoint {path}: {error}") from None
    if not isinstance(payload, dict):
        raise CheckpointError(f"checkpoint {path} is not a d3rqn checkpoint")
    missing = [name for name in required if name not in payload]
    if missing:
        raise CheckpointError(f"checkpoint {path} lacks {', '.join(missing)}")
    return payload
