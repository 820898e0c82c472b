"""One typed configuration for every process, with the paper's values as defaults: the schema.

A config is a tree of dataclasses, one per section (``Config.learner``, ``Config.exploration.bmc``, ...);
a strategy's section is declared next to its rule (common/exploration/). Each field is declared with
``option()`` (common/schema/fields.py), whose one documentation string (with the unit and choices) is the
flag's ``--help`` line, and every section checks its values (``validate``); a bad one raises
``ConfigError`` whose one-line message names the key.

A config is built from a preset (common/presets.py), then a TOML file, then dotted keys
(common/config_values.py), which the command line's flags (``--learner.lr 3e-4``,
``--exploration.bmc.alpha0 25``) set (common/config_cli.py).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from common.exploration.bmc import BmcConfig
from common.exploration.boltzmann import MaxBoltzmannConfig, SoftmaxConfig
from common.exploration.epsilon_greedy import ConstantEpsilonConfig, DecreasingEpsilonConfig
from common.exploration.names import STRATEGIES
from common.exploration.vdbe import VdbeConfig
from common.schema.fields import ConfigError, check, check_positive, option
from common.process_config import ActorConfig, RecorderConfig, RunConfig, TransportConfig
from common.sim_config import EnvConfig, EvaluationConfig
from common.wire.weights_encoding import WEIGHTS_ENCODINGS


@dataclass
class NetworkConfig:
    """The D3RQN: three convolutions, an LSTM and a dueling head (learner and actors alike)."""

    frame_height: int = option(66, "height of the camera image the network takes", "px")
    frame_width: int = option(200, "width of the camera image the network takes", "px")
    frame_channels: int = option(3, "colour channels of the camera image (3: RGB)")
    lstm_units: int = option(512, "LSTM units; the output is split in two halves, for the dueling value and "
                                  "advantage streams")
    n_actions: int = option(5, "discrete steering actions (the Q-values the network outputs)")
    device: str = option("auto", "where the learner's networks run (actors and evaluation use the CPU): auto picks "
                         "CUDA when available, else the CPU",
                         choices=("auto", "cpu", "cuda[:N]"))

    def validate(self) -> None:
        check_positive(self, "frame_height", "frame_width", "frame_channels", "n_actions")
        # The three VALID convolutions (8/4, 4/2, 3/1) need at least 36 pixels per side.
        check(self.frame_height >= 36, "frame_height", f"must be >= 36 for the convolutions, got {self.frame_height}")
        check(self.frame_width >= 36, "frame_width", f"must be >= 36 for the convolutions, got {self.frame_width}")
        check(self.lstm_units > 0 and self.lstm_units % 2 == 0, "lstm_units", "must be a positive even number (it is split in two dueling halves)")
        check(self.device == "auto" or self.device == "cpu" or self.device.startswith("cuda"), "device", "must be 'auto', 'cpu' or 'cuda[:N]'")


START_RULES = ("strategy", "episodes", "steps")  # pace.start_by


@dataclass
class PaceConfig:
    """The run's pace, which the replay's rate limiter keeps (replay/rate_limiter.py): when updates start, one
    update per so many env steps, how far either side may run ahead, and when the run ends."""

    env_steps_per_update: float = option(
        4.0, "one update per this many env steps of the whole system, counted from the start of updates; the "
             "replay's rate limiter holds whichever side runs ahead (pace.error_buffer_updates)", "env steps")
    start_episodes: int = option(999, "updates start the moment the replay holds this many episodes", "episodes")
    start_steps: int = option(50_000, "used instead of start_episodes when the learner's strategy is decreasing "
                                      "epsilon, or for every strategy with start_by = steps", "env steps")
    start_by: str = option(
        "strategy", "what starts the updates: strategy (the paper's rule: decreasing epsilon at start_steps env "
                    "steps, the others at start_episodes episodes), episodes (every strategy at start_episodes) or "
                    "steps (every strategy at start_steps: the same point for all, as a comparison wants)",
        choices=START_RULES)
    total_env_steps: int = option(1_000_000, "the run ends here: actors hold, episodes in flight are taken until "
                                             "the learner is served the updates they pay for, then the replay "
                                             "closes the run (later episodes refused, counted as late_episodes) "
                                             "and the learner stops once it has paid for every step taken",
                                  "env steps")
    error_buffer_updates: float = option(
        50.0, "the rate limiter (replay/rate_limiter.py, after Reverb's SampleToInsertRatio) keeps one update per "
              "pace.env_steps_per_update env steps: it holds trace batches while the learner is this many updates "
              "ahead, and the actors' next episode while it is this many (or hold_updates, if more) behind. The "
              "whole run's ratio is off by at most this many updates. A buffer of at least the updates the budget pays for (1e9) holds nobody: the "
              "run is unpaced and ends at the budget", "updates")
    hold_updates: float = option(
        1500.0, "the actors hold their next episode while the learner is more than this many updates behind "
               "(never fewer than error_buffer_updates). A let-go actor delivers nothing until its whole next "
               "episode ends, so a fast learner needs this lead to keep busy (docs/architecture.md, the pace of a "
               "fast learner); it does not change the run's ratio at the end, which the learner pays for before "
               "the run closes", "updates")

    def validate(self) -> None:
        check_positive(self, "env_steps_per_update", "total_env_steps")
        check(self.start_episodes >= 1, "start_episodes", "must be >= 1")
        check(self.start_steps >= 0, "start_steps", "must be >= 0")
        check(self.start_by in START_RULES, "start_by", f"must be one of {', '.join(START_RULES)}")
        check(self.error_buffer_updates >= 1, "error_buffer_updates",
              f"must be >= 1 (a narrower buffer can block both sides), got {self.error_buffer_updates!r}")
        check(self.hold_updates >= 0, "hold_updates", f"must be >= 0, got {self.hold_updates!r}")


@dataclass
class ReplayConfig:
    """The replay service: the episode store, its memory cap, snapshots (its rate limiter keeps the pace)."""

    capacity: int = option(1000, "episodes the replay holds; beyond it the oldest is dropped (the paper studies "
                                 "1,000 and 2,000)", "episodes")
    # 4.1 KB a frame at most, measured on random drives: front camera 2.6 KB, top-down 3.5 KB.
    memory_budget_mb: float = option(
        16384.0, "cap on the compressed frames plus metadata the replay holds, not an allocation; 16 GB holds 2,000 "
                 "episodes of env.max_steps = 2,000 steps at up to 4.1 KB a frame. At start the replay logs how many "
                 "full-length episodes fit and warns loudly when fewer than capacity do; once episodes arrive it "
                 "checks again with the measured frame size", "MB")
    frame_kb_estimate: float = option(3.2, "size of one compressed frame, for the start-up memory check until "
                                           "frames are measured", "KB")
    max_message_mb: float = option(64.0, "larger episode messages are rejected", "MB")
    max_batch_size: int = option(256, "largest trace batch one query may ask for", "traces")
    stats_period_s: float = option(1.0, "how often the replay publishes its stats and checks the actors' hold", "s")
    log_period_s: float = option(10.0, "how often the replay logs a status line", "s")
    seed: int = option(0, "seed of the replay's trace sampling")
    sample_by_steps: bool = option(False, "beyond the paper: every trace the store holds equally likely (an episode in "
                                          "proportion to its starts), not an episode uniformly, then a start (the paper's); "
                                          "at a short budget the random phase's short episodes are otherwise half the "
                                          "traces drawn (docs/results/buffer-fill.md)")
    reward_limit: float = option(100.0, "an episode (or trace batch) with a reward of larger magnitude is refused as "
                                        "absurd; the env's rewards exp(-beta d) lie in [0, 1]")
    snapshot_period_s: float = option(
        30.0, "how often the replay writes its episodes and counters to <runs_dir>/<run>/replay/snapshot/ (and at "
              "exit); only episodes new since the last snapshot are written, `replay --resume` restores them; 0 turns "
              "snapshots off", "s")

    def validate(self) -> None:
        check_positive(self, "capacity", "memory_budget_mb", "frame_kb_estimate", "max_message_mb",
                       "max_batch_size", "stats_period_s", "log_period_s", "reward_limit")
        check(self.snapshot_period_s >= 0, "snapshot_period_s", "must be >= 0 (0: no snapshots)")


UPDATE_PATHS = ("auto", "trace", "trace-split", "autograd")
LEARNER_PRECISIONS = ("float32", "bfloat16", "auto")  # learner.precision


@dataclass
class LearnerConfig:
    """Training: the double dueling recurrent Q-learning update, weights and checkpoints."""

    lr: float = option(1e-4, "Adam's learning rate")
    gamma: float = option(0.99, "discount factor of future rewards, in [0, 1]")
    tau: float = option(0.001, "soft target update before every gradient step: target <- tau online + (1 - tau) "
                               "target, in (0, 1]")
    batch_size: int = option(10, "traces per batch", "traces")
    trace_length: int = option(10, "steps per trace (trace_length + 1 observations)", "steps")
    n_mask: int = option(7, "leading errors of each trace that are masked out of the loss (the LSTM's warm-up)",
                         "steps")
    weights_every: int = option(50, "broadcast the weights to the actors every this many updates", "updates")
    weights_period_s: float = option(
        0.0, "also broadcast the weights once this long has passed since the last broadcast (after an update), "
             "whichever of this and weights_every comes first: a fast learner broadcasts by time, a slow one by "
             "updates; 0: by updates only", "s")
    weights_min_period_s: float = option(
        0.8, "but never broadcast sooner than this after the last broadcast: a learner faster than weights_every "
             "updates in this time broadcasts by time (the default leaves the paper's every 50 updates to a learner "
             "of up to 62 updates/s). Each broadcast costs every actor a pause of its loop to load the weights and "
             "CPU to decode them (docs/architecture.md, the pace of a fast learner); 0: no floor", "s")
    weights_encoding: str = option(
        "float32", "how weights travel to the actors (broadcasts and the latest-weights answer): float32 (whole; "
                   "48.6 MB at the paper's sizes), or half the size as float16 or bfloat16, whose greedy actions "
                   "differ from float32's within the tolerance docs/architecture.md states", choices=tuple(WEIGHTS_ENCODINGS))
    checkpoint_every: int = option(5_000, "write checkpoints/latest.pt every this many updates", "updates")
    checkpoint_every_s: float = option(
        600.0, "also write checkpoints/latest.pt once this long has passed since the last one (after an update), "
               "whichever of this and checkpoint_every comes first: bounds the updates a killed learner loses and "
               "makes again; 0: by updates only", "s")
    keep_every: int = option(
        0, "keep the policy (the online weights, with the run's updates, env steps and wall time) in the run folder's "
           "policies/ every this many updates, and at the end, for greedy learning curves (`evaluate --curve`); "
           "each file holds one network (48.6 MB at the paper's sizes); 0: not by updates", "updates")
    keep_every_s: float = option(
        0.0, "also keep the policy once this long has passed since the last kept one (after an update), whichever of "
             "this and keep_every comes first; 0: not by time", "s")
    keep_encoding: str = option(
        "float32", "how kept policies hold their weights: float32 (as trained), or, beyond the paper, float16 or "
                   "bfloat16 at half the disk (24.3 MB at the paper's sizes; a long run's largest part): the curve then "
                   "reads the rounded weights, as a shipped policy's (docs/evaluation-curves.md)",
        choices=tuple(WEIGHTS_ENCODINGS))
    lr_decay_from: int = option(
        0, "beyond the paper: from this many updates on, Adam's rate falls linearly to lr x lr_final_scale at "
           "lr_decay_to updates, then stays there: a smaller step late in a run (learner/step_size.py); 0: off, "
           "the paper's constant rate", "updates")
    lr_decay_to: int = option(0, "with lr_decay_from: the update at which the rate reaches lr x lr_final_scale",
                              "updates")
    lr_final_scale: float = option(0.1, "with lr_decay_from: the rate at lr_decay_to and after, as a share of lr, "
                                        "in (0, 1]")
    grad_clip_norm: float = option(
        0.0, "beyond the paper: scale each update's gradient to a global norm of at most this (Ape-X and R2D2 clip "
             "at 40), bounding the steps a rare large error makes; 0: off, the paper's unclipped Adam step")
    keep_target: bool = option(
        False, "beyond the paper: also keep the target network (a Polyak average of the online weights over about "
               "1/tau updates) beside each kept policy from keep_shadows_from on, as kind target in "
               "policies/target/; nothing the actors or the loss see changes (docs/evaluation-curves.md)")
    ema_updates: int = option(
        0, "beyond the paper: hold an exponential moving average of the online weights over about this many updates "
           "(each update moves it 1/ema_updates of the way to the online weights; it steps every 10 updates, as far "
           "as 10 such steps go), in float32 and checkpointed, "
           "and keep it beside each kept policy from keep_shadows_from on, as kind ema in policies/ema/; the actors "
           "and the loss never see it. 0: off", "updates")
    keep_shadows_from: int = option(
        0, "keep the target and EMA policies (keep_target, ema_updates) only beside the policies kept at this many "
           "updates or later: a curve reads them late in a run, and each is one network's file", "updates")
    prefetch: int = option(2, "batch requests kept in flight to the replay", "batches")
    torch_threads: int = option(
        0, "torch's CPU threads; 0 keeps torch's default (all cores): paced actors leave the learner most of the "
           "CPU. On a host shared with busy processes, fewer threads avoid oversubscription, which slows an update "
           "several times over", "threads")
    update_path: str = option(
        "auto", "how an update computes its passes (learner/update.py): trace (hand-written passes, CPU-tuned), "
                "trace-split (the same, the target pass on a helper thread with half the torch threads), autograd "
                "(nn.LSTM under autograd; cuDNN on CUDA), or auto: each timed on the first batch (a second or two at "
                "the paper's sizes), the fastest kept for the process", choices=UPDATE_PATHS)
    n_step: int = option(
        1, "beyond the paper: n-step double-Q targets, the sum of this many discounted rewards before the "
           "bootstrap (a terminal stops both; the trace's end shortens the window; the 2,000-step cut "
           "bootstraps). 1 is the paper's one-step target", "steps")
    stored_state: bool = option(
        False, "beyond the paper (R2D2): actors record their LSTM state before each step in the episode (h and c "
               "in float16: 4 x network.lstm_units bytes a step, 2,048 at the paper's sizes), the replay keeps it, "
               "and the learner starts each trace from the stored state instead of a zero state; the first "
               "learner.burn_in steps then count no error, in place of n_mask")
    burn_in: int = option(
        0, "with stored_state: leading steps of each trace that run from the stored state without gradient and "
           "count no error (R2D2's burn-in), before the steps that train; must lie in [0, trace_length)", "steps")
    shift_pad: int = option(
        0, "beyond the paper: random-shift augmentation of the frames the learner trains on (DrQ, Kostrikov et al. "
           "2020; DrQ(epsilon) in Dopamine's Atari-100k configurations pads by 4): each trace's frames are padded by "
           "this many pixels, repeating the edge, and cropped back to their size at one random offset for all its "
           "steps, the same for its online and target passes (learner/frame_shift.py), drawn from learner.seed; "
           "the actors and the evaluation see the frames as they are. 0: off, the paper's frames", "px")
    precision: str = option(
        "float32", "beyond the paper: the number format of the update's convolutions and LSTM input projection, "
                   "forward and backward (the trace paths): float32 (the paper's); bfloat16 (master weights, Adam's "
                   "state, the recurrence, the head, targets and the loss stay float32; refused at start on a CPU "
                   "that cannot run it); or auto (bfloat16 where the CPU does it natively, AMX or AVX512-BF16, and "
                   "the best of 5 interleaved timing rounds on the first batch, by CPU time, is at least 1.3x faster, so a busy "
                   "neighbour does not decide it; float32 otherwise, and with the autograd path, with a log line)",
        choices=LEARNER_PRECISIONS)
    log_period_s: float = option(10.0, "how often the learner logs and publishes its metrics", "s")
    seed: int = option(0, "seed of the network's initial weights")
    silence_reopen_s: float = option(
        60.0, "reopen the Zenoh session once no word of the replay (replay/stats, replay/rate, a batch) has come "
              "for this long, and again after each further span: a session can stay half-alive, its batch "
              "requests arriving while nothing comes back (common/hub_link.py)", "s")

    @property
    def masked_steps(self) -> int:
        """Leading errors of each trace left out of the loss: n_mask from the zero state (the paper's), burn_in
        from a stored state."""
        return self.burn_in if self.stored_state else self.n_mask

    def validate(self) -> None:
        check(self.precision in LEARNER_PRECISIONS, "precision", f"must be one of {', '.join(LEARNER_PRECISIONS)}")
        check(not (self.precision == "bfloat16" and self.update_path == "autograd"), "precision",
              "bfloat16 runs on the trace paths only: set learner.update_path to trace, trace-split or auto")
        check_positive(self, "lr", "batch_size", "trace_length", "weights_every", "checkpoint_every", "prefetch", "log_period_s",
                       "silence_reopen_s")
        check(0.0 <= self.gamma <= 1.0, "gamma", "must lie in [0, 1]")
        check(0.0 < self.tau <= 1.0, "tau", "must lie in (0, 1]")
        check(0 <= self.n_mask < self.trace_length, "n_mask", "must lie in [0, trace_length)")
        check(1 <= self.n_step <= self.trace_length, "n_step", "must lie in [1, trace_length]")
        check(0 <= self.burn_in < self.trace_length, "burn_in", "must lie in [0, trace_length)")
        check(self.stored_state or self.burn_in == 0, "burn_in",
              "needs learner.stored_state true (a trace from the zero state masks learner.n_mask steps instead)")
        check(self.torch_threads >= 0, "torch_threads", "must be >= 0 (0: torch's default)")
        check(self.update_path in UPDATE_PATHS, "update_path", f"must be one of {', '.join(UPDATE_PATHS)}")
        check(self.weights_period_s >= 0, "weights_period_s", "must be >= 0 (0: by updates only)")
        check(self.weights_min_period_s >= 0, "weights_min_period_s", "must be >= 0 (0: no floor)")
        check(self.checkpoint_every_s >= 0, "checkpoint_every_s", "must be >= 0 (0: by updates only)")
        check(self.keep_every >= 0, "keep_every", "must be >= 0 (0: not by updates)")
        check(self.keep_every_s >= 0, "keep_every_s", "must be >= 0 (0: not by time)")
        check(self.weights_encoding in WEIGHTS_ENCODINGS, "weights_encoding",
              f"must be one of {', '.join(WEIGHTS_ENCODINGS)}")
        check(self.keep_encoding in WEIGHTS_ENCODINGS, "keep_encoding", f"must be one of {', '.join(WEIGHTS_ENCODINGS)}")
        check(self.ema_updates >= 0, "ema_updates", "must be >= 0 (0: off)")
        check(self.lr_decay_from >= 0, "lr_decay_from", "must be >= 0 (0: off)")
        check(self.lr_decay_from == 0 or self.lr_decay_to > self.lr_decay_from, "lr_decay_to",
              "must exceed learner.lr_decay_from when the decay is on")
        check(0.0 < self.lr_final_scale <= 1.0, "lr_final_scale", "must lie in (0, 1]")
        check(self.grad_clip_norm >= 0, "grad_clip_norm", "must be >= 0 (0: off)")
        check(self.keep_shadows_from >= 0, "keep_shadows_from", "must be >= 0")
        check(self.shift_pad >= 0, "shift_pad", f"must be >= 0 pixels (0: off), got {self.shift_pad}")


@dataclass
class ExplorationConfig:
    """The exploration strategy the learner drives and the actors follow, and each one's parameters."""

    strategy: str = option("bmc", "the exploration strategy (the paper's seven; common/exploration/)",
                           choices=STRATEGIES)
    constant: ConstantEpsilonConfig = field(default_factory=ConstantEpsilonConfig)
    decreasing: DecreasingEpsilonConfig = field(default_factory=DecreasingEpsilonConfig)
    vdbe: VdbeConfig = field(default_factory=VdbeConfig)
    bmc: BmcConfig = field(default_factory=BmcConfig)
    softmax: SoftmaxConfig = field(default_factory=SoftmaxConfig)
    max_boltzmann: MaxBoltzmannConfig = field(default_factory=MaxBoltzmannConfig)

    def validate(self) -> None:
        check(self.strategy in STRATEGIES, "strategy", f"must be one of {', '.join(STRATEGIES)}")


@dataclass
class Config:
    run: RunConfig = field(default_factory=RunConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    learner: LearnerConfig = field(default_factory=LearnerConfig)
    pace: PaceConfig = field(default_factory=PaceConfig)
    exploration: ExplorationConfig = field(default_factory=ExplorationConfig)
    env: EnvConfig = field(default_factory=EnvConfig)
    actor: ActorConfig = field(default_factory=ActorConfig)
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)
    transport: TransportConfig = field(default_factory=TransportConfig)
    recorder: RecorderConfig = field(default_factory=RecorderConfig)

    def validate(self) -> "Config":
        for path, section in sections(self):
            if section is self:
                continue
            try:
                section.validate()
            except ConfigError as error:
                raise ConfigError(f"{path}.{error}" if path else str(error)) from None
        check(self.pace.start_episodes <= self.replay.capacity, "pace.start_episodes",
              f"{self.pace.start_episodes} exceeds replay.capacity {self.replay.capacity}: updates would never start")
        check(self.actor.silence_hold_s >= 3 * self.replay.stats_period_s, "actor.silence_hold_s",
              f"must be >= 3 replay.stats_period_s ({3 * self.replay.stats_period_s:g} s): the replay announces "
              "its word that often, and a late word or two is no silence")
        return self


def sections(config: Any, path: str = ""):
    """Every section of a config with its dotted path, the config itself ("") first."""
    yield path, config
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            yield from sections(value, f"{path}.{f.name}" if path else f.name)
