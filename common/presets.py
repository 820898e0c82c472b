"""The presets a config is built from (``--preset NAME``): values over the schema's defaults
(common/config.py), by dotted key, each with what it is for."""

from __future__ import annotations

from typing import Any


class Preset(dict):
    """Values over the dataclass defaults, by dotted key, and what the preset is for (shown by --help)."""

    def __init__(self, doc: str, values: dict[str, Any]) -> None:
        super().__init__(values)
        self.doc = doc


LOCAL = {
    "pace.total_env_steps": 60_000,
    "pace.start_steps": 10_000,
    "learner.checkpoint_every": 1_000,
    "learner.keep_every": 1_000,  # about 12 policies a run for its greedy curve
    "exploration.decreasing.n_start": 10_000,
    "exploration.decreasing.n_ann": 20_000,
    "exploration.decreasing.n_max": 60_000,
}

# The grid's protocol (docs/experiments.md): every strategy starts updating at the same env step, about where the
# paper's 999 random episodes end here, and trains 30,000 updates at the paper's 1 update per 4 env steps.
GRID_START_STEPS = 28_000
GRID_UPDATES = 30_000
GRID_TOTAL_ENV_STEPS = GRID_START_STEPS + 4 * GRID_UPDATES
# The paper's first slope of decreasing epsilon is 400,000 of its 950,000 steps after the start: 42%.
GRID_SHADOWS_FROM = 20_000  # the late curve (actor/evaluation/curve.py LATE_FROM)
GRID_DECREASING_N_ANN = round((GRID_TOTAL_ENV_STEPS - GRID_START_STEPS) * 400_000 / 950_000)

DRIVE = {
    **LOCAL,
    "pace.start_by": "steps",
    "pace.start_steps": GRID_START_STEPS,
    "pace.total_env_steps": GRID_TOTAL_ENV_STEPS,
    "learner.precision": "auto",
    # The pace the grid's first runs trained at, pinned so that every cell on every machine acts alike: actors
    # held 50 updates behind, weights every 50 updates whatever the learner's speed (a cell is its updates and
    # ratio, not the clock). The defaults since keep a fast learner busier (docs/architecture.md).
    "pace.hold_updates": 50.0,
    "learner.weights_min_period_s": 0.0,
    "exploration.decreasing.n_start": GRID_START_STEPS,
    "exploration.decreasing.n_ann": GRID_DECREASING_N_ANN,
    "exploration.decreasing.n_max": GRID_TOTAL_ENV_STEPS,
    # Beyond the paper, read beside it and changing nothing the actors or the loss see: the target network and a
    # moving average over 5,000 updates, kept from 20,000 updates on, where the first grid's policies swung
    # (a 10,000-update average would still weigh the weights from before 10,000 updates, not yet driving, by 37%
    # there; this one by 13.5%, and by 4-9% at the choice's 26,000-30,000).
    "learner.keep_target": True,
    "learner.ema_updates": 5_000,
    "learner.keep_shadows_from": GRID_SHADOWS_FROM,
}

PRESETS: dict[str, Preset] = {
    "paper": Preset("the paper's values, which are the defaults", {}),
    "local": Preset(
        "a quick look on a 2-core CPU machine (about 30 minutes, a car that does not drive yet): the paper's agent, "
        "buffer and ratio, with the run cut to 60,000 steps and the decreasing schedule scaled to that length", LOCAL),
    "fast": Preset(
        "the local preset trained past the knee, with the learner in bfloat16 where the CPU does it natively and "
        "measures faster (the study, docs/results/study.md). Beyond the paper: learner.precision auto (the same "
        "math; the bfloat16 runs' greedy curves lay within the float32 runs' seed spread) and the run's length, "
        "112,000 env steps, about 21,000 updates (by then 3 of the study's 4 runs of the paper's learner drove, "
        "the fourth 189 updates later); as in local, the agent, buffer and ratio are the paper's", {
            **LOCAL,
            "pace.total_env_steps": 112_000,
            "learner.precision": "auto",
        }),
    "drive": Preset(
        "the main job and every cell of the grid (deploy/grid/experiments.py): the paper's agent, buffer and ratio, "
        "30,000 updates (past the knee of 15,000-24,000 where the paper's learner first drives), updates starting "
        "at 28,000 env steps for every strategy, decreasing epsilon's schedule scaled to that budget, "
        "learner.precision auto (beyond the paper: bfloat16 where the CPU does it natively and measures faster); "
        "beyond the paper too, kept beside the online policies from 20,000 updates on and read on their own: the "
        "target network and a moving average of the online weights over 5,000 updates",
        DRIVE),
    "smoke": Preset(
        "seconds-long runs for tests: tiny buffer, short episodes, early updates", {
            "replay.capacity": 50,
            "replay.stats_period_s": 0.5,
            "pace.error_buffer_updates": 2.0,  # short runs: the run's ratio within 2 updates
            "pace.hold_updates": 2.0,  # as tight: 700 would be 14,000 of the 20,000 steps, and hold nobody
            "learner.batch_size": 4,
            "pace.env_steps_per_update": 20.0,  # the random phase's backlog clears in seconds
            "pace.start_episodes": 2,
            "pace.start_steps": 100,
            "pace.total_env_steps": 20_000,
            "learner.weights_every": 5,
            "learner.weights_min_period_s": 0.0,  # every 5 updates, however fast: the tests watch the versions
            "learner.checkpoint_every": 50,
            "learner.keep_every": 100,
            "learner.log_period_s": 1.0,
            "exploration.decreasing.n_start": 100,
            "exploration.decreasing.n_ann": 800,
            "exploration.decreasing.n_max": 2_000,
            "env.max_steps": 60,
            "actor.log_period_s": 1.0,
            "evaluation.episodes_per_start": 1,
            "evaluation.max_steps": 60,
            "evaluation.workers": 1,
            "evaluation.envs_per_worker": 2,
        }),
}
