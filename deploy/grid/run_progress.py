"""What a run's folder says of its training, for the grid runner: how much of its budget it has trained,
whether its stack trains now, and the logs of an attempt that never checkpointed, set aside."""

from __future__ import annotations

import datetime
import shutil
from pathlib import Path

from common.run_dir import RunDir, RunStatus, StatusError
from deploy.grid.grid_cells import TRAIN, ExperimentError, checkpoint_env_steps, next_step


def set_aside_stale_files(run_dir: Path) -> Path | None:
    """Moves the logs of an attempt that never checkpointed out of the way of a fresh start.

    Otherwise the new recorder would write traffic-2.mcap next to the old file and the
    figures would read both as one run.
    """
    run = RunDir(run_dir)
    stale = run.wire_log_segments() + [path for path in [run.logs] if path.is_dir()]
    if not stale:
        return None
    target = run.abandoned(datetime.datetime.now().strftime("%Y%m%d-%H%M%S"))
    target.mkdir(parents=True)
    for path in stale:
        shutil.move(path, target / path.name)
    return target


def trained_share(run_dir: Path, budget: int) -> float:
    """How much of its budget (env steps) a run has trained: all once past its training, else what its
    checkpoint holds (nothing without a readable one)."""
    checkpoint = RunDir(run_dir).checkpoint
    try:
        if not checkpoint.is_file():
            return 0.0 if next_step(run_dir, budget) == TRAIN else 1.0
        return min(1.0, checkpoint_env_steps(checkpoint) / budget)  # whatever its later steps can read
    except ExperimentError:
        return 0.0


def trains_since(run: RunDir, since: float) -> bool:
    """Whether the run's stack, started at `since` (time.time()), says it trains: a resumed run's old
    status.json says "stopped" until the new stack rewrites it."""
    try:
        status = RunStatus.read(run.status)
    except StatusError:
        return False
    return status.time >= since and status.training()
