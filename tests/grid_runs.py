"""Run folders and evaluations as the grid's steps leave them, for the tests of the runner, the export and
the comparison."""

from __future__ import annotations

import math
from pathlib import Path

from common.analysis.stats import EvaluationEpisode, summarise_all
from common.analysis.tables import write_evaluation
from common.checkpoint import save_checkpoint
from common.config_values import load_config, to_toml

EDGES = [0.0, 0.25, 0.5, 0.75, 1.0]


def episode(policy: str, start_set: str, length: int, end: str, bins: tuple[int, ...], start_index: int = 0,
            progress_m: float = math.nan, streets: float = math.nan, junctions: float = math.nan) -> EvaluationEpisode:
    return EvaluationEpisode(policy=policy, start_set=start_set, start_index=start_index, trial=0, seed=7,
                             length=length, end=end, episode_return=0.5 * length, reward_bin_counts=bins,
                             actions_digest=f"d{length}", progress_m=progress_m, streets=streets, junctions=junctions)


def fake_evaluation(directory: Path, greedy_lengths: list[int], random_length: int = 4, updates: int | None = None,
                    progress: bool = False, privileged_length: int | None = None) -> Path:
    """Greedy episodes of the given lengths on both sets (a length of 100 reaches the cap, 50 stalls), one
    random each (and one of the privileged driver if given); with progress, each greedy episode drove 0.9 m
    per step and visited a street per 25 steps (at least one) and a junction fewer."""
    episodes = []
    for start_set in ("train", "test"):
        for number, length in enumerate(greedy_lengths):
            end = {100: "cap", 50: "stalled"}.get(length, "collision")
            streets = max(1, length // 25)
            coverage = (streets, streets - 1) if progress else (math.nan, math.nan)
            episodes.append(episode("greedy", start_set, length, end, (0, 0, 0, length), number,
                                    0.9 * length if progress else math.nan, *coverage))
        episodes.append(episode("random", start_set, random_length, "offroad", (random_length, 0, 0, 0)))
        if privileged_length is not None:
            episodes.append(episode("privileged", start_set, privileged_length, "cap", (0, 0, 0, privileged_length)))
    facts = {} if updates is None else {"updates": str(updates)}
    write_evaluation(directory, episodes, summarise_all(episodes), EDGES, facts, 1, "")
    return directory


def make_smoke_run(run_dir: Path, env_steps: int | None = None, evaluated: bool = False, updates: int | None = None,
             strategy: str = "bmc", capacity: int = 50, seed: int = 0) -> Path:
    """A run folder as the stack and evaluate leave it: its config, a checkpoint with this clock, an evaluation."""
    run_dir.mkdir(parents=True, exist_ok=True)
    config = load_config("smoke", overrides={"run.name": run_dir.name, "exploration.strategy": strategy,
                                             "replay.capacity": capacity, "run.seed": seed})
    (run_dir / "config.toml").write_text(to_toml(config))
    if env_steps is not None:
        save_checkpoint(run_dir / "checkpoints", {"clock": {"env_steps": env_steps}, "learner": {"updates": 7}})
    if evaluated:
        fake_evaluation(run_dir / "evaluation", [100, 50], updates=updates)
    return run_dir
