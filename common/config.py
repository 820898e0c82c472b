"""One typed configuration for every process, with the paper's values as defaults.

A config is a tree of dataclasses. It is built from a preset, then a TOML file,
then command-line flags named after the dotted path of a field
(``--learner.lr 3e-4``, ``--exploration.bmc.alpha0 25``). Every value is
checked against its field's type and range; a bad one raises ``ConfigError``
whose one-line message names the key.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import math
import sys
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


class ConfigError(ValueError):
    """A configuration value, file or flag is wrong; the message names the key."""


STRATEGIES = (
    "constant",
    "decreasing",
    "vdbe",
    "bmc",
    "softmax",
    "max_boltzmann",
    "vdbe_softmax",
)


@dataclass
class NetworkConfig:
    frame_height: int = 66
    frame_width: int = 200
    frame_channels: int = 3
    lstm_units: int = 512
    n_actions: int = 5
    device: str = "auto"  # "auto" picks CUDA when available, else CPU

    def validate(self) -> None:
        _positive(self, "frame_height", "frame_width", "frame_channels", "n_actions")
        # The three VALID convolutions (8/4, 4/2, 3/1) need at least 36 pixels per side.
        _check(self.frame_height >= 36, "frame_height", f"must be >= 36 for the convolutions, got {self.frame_height}")
        _check(self.frame_width >= 36, "frame_width", f"must be >= 36 for the convolutions, got {self.frame_width}")
        _check(self.lstm_units > 0 and self.lstm_units % 2 == 0, "lstm_units", "must be a positive even number (it is split in two dueling halves)")
        _check(self.device == "auto" or self.device == "cpu" or self.device.startswith("cuda"), "device", "must be 'auto', 'cpu' or 'cuda[:N]'")


@dataclass
class ReplayConfig:
    capacity: int = 1000  # episodes; the paper studies 1,000 and 2,000
    # Compressed frames plus metadata; a cap, not an allocation. 16 GB holds 2,000 episodes of
    # env.max_steps = 2,000 steps at up to 4.1 KB a frame (measured on random drives: front
    # camera 2.6 KB, top-down 3.5 KB). At start
    # the replay logs how many full-length episodes fit, and warns loudly when fewer than
    # `capacity` do; once episodes arrive it checks again with the measured frame size.
    memory_budget_mb: float = 16384.0
    frame_kb_estimate: float = 3.2  # one compressed frame, for the start-up check until measured
    max_message_mb: float = 64.0  # larger episode messages are rejected
    max_batch_size: int = 256  # largest trace batch one query may ask for
    # The rate limiter (replay/rate_limiter.py, after Reverb's SampleToInsertRatio) keeps one
    # update per learner.env_steps_per_update env steps: it holds trace batches while the learner
    # is this many updates ahead, and holds the actors' next episode while it is this many behind.
    # The whole run's ratio is off by at most this many updates. A buffer of at least the updates
    # the budget pays for (1e9) holds nobody: the run is unpaced and ends at the budget.
    error_buffer_updates: float = 50.0
    stats_period_s: float = 1.0
    log_period_s: float = 10.0
    seed: int = 0
    # An episode (or trace batch) with a reward of larger magnitude is refused as absurd; the
    # env's rewards exp(-beta d) lie in [0, 1].
    reward_limit: float = 100.0
    # The replay writes its episodes and counters to <runs_dir>/<run>/replay/snapshot/ this often
    # (and at exit); only episodes new since the last snapshot are written. `replay --resume`
    # restores it. 0 turns snapshots off.
    snapshot_period_s: float = 30.0

    def validate(self) -> None:
        _positive(self, "capacity", "memory_budget_mb", "frame_kb_estimate", "max_message_mb",
                  "max_batch_size", "stats_period_s", "log_period_s", "reward_limit")
        _check(self.error_buffer_updates >= 1, "error_buffer_updates",
               f"must be >= 1 (a narrower buffer can block both sides), got {self.error_buffer_updates!r}")
        _check(self.snapshot_period_s >= 0, "snapshot_period_s", "must be >= 0 (0: no snapshots)")


UPDATE_PATHS = ("auto", "trace", "trace-split", "autograd")


@dataclass
class LearnerConfig:
    lr: float = 1e-4
    gamma: float = 0.99
    tau: float = 0.001  # soft target update before every gradient step
    batch_size: int = 10  # traces per batch
    trace_length: int = 10  # steps per trace (trace_length + 1 observations)
    n_mask: int = 7  # leading errors of each trace that are masked out
    # One update per this many env steps of the whole system, counted from the start of updates;
    # the replay's rate limiter holds whichever side runs ahead (replay.error_buffer_updates).
    env_steps_per_update: float = 4.0
    start_episodes: int = 999  # updates start the moment the replay holds this many episodes
    start_steps: int = 50_000  # used instead when the learner's strategy is decreasing epsilon
    total_env_steps: int = 1_000_000  # the run ends here: actors hold, the learner pays the last steps
    weights_every: int = 50  # broadcast weights every K updates
    checkpoint_every: int = 5_000  # updates
    prefetch: int = 2  # batch requests kept in flight
    # 0 keeps torch's default (all cores): paced actors leave the learner most of the CPU.
    # On a host shared with busy processes, fewer threads avoid oversubscription, which
    # slows an update several times over.
    torch_threads: int = 0
    # How an update computes its passes (learner/update.py): "trace" (hand-written passes, CPU-tuned),
    # "trace-split" (the same, the target pass on a helper thread with half the torch threads),
    # "autograd" (nn.LSTM under autograd; cuDNN on CUDA), or "auto": each timed on the first batch
    # (a second or two at the paper's sizes), the fastest kept for the process.
    update_path: str = "auto"
    log_period_s: float = 10.0
    seed: int = 0

    def validate(self) -> None:
        _positive(self, "lr", "batch_size", "trace_length", "env_steps_per_update",
                  "total_env_steps", "weights_every", "checkpoint_every", "prefetch", "log_period_s")
        _check(0.0 <= self.gamma <= 1.0, "gamma", "must lie in [0, 1]")
        _check(0.0 < self.tau <= 1.0, "tau", "must lie in (0, 1]")
        _check(0 <= self.n_mask < self.trace_length, "n_mask", "must lie in [0, trace_length)")
        _check(self.start_episodes >= 1, "start_episodes", "must be >= 1")
        _check(self.start_steps >= 0, "start_steps", "must be >= 0")
        _check(self.torch_threads >= 0, "torch_threads", "must be >= 0 (0: torch's default)")
        _check(self.update_path in UPDATE_PATHS, "update_path", f"must be one of {', '.join(UPDATE_PATHS)}")


@dataclass
class ConstantEpsilonConfig:
    epsilon: float = 0.05

    def validate(self) -> None:
        _probability(self, "epsilon")


@dataclass
class DecreasingEpsilonConfig:
    eps_start: float = 1.0
    eps_last: float = 0.1
    eps_end: float = 0.01
    n_start: int = 50_000
    n_ann: int = 400_000
    n_max: int = 1_000_000

    def validate(self) -> None:
        _probability(self, "eps_start", "eps_last", "eps_end")
        _check(self.n_start >= 0, "n_start", "must be >= 0")
        _check(self.n_ann > 0, "n_ann", "must be > 0")
        _check(self.n_max > self.n_start + self.n_ann, "n_max", "must exceed n_start + n_ann")


@dataclass
class VdbeConfig:
    lam: float = 0.2  # 1 / number of actions
    nu: float = 1.0  # inverse sensitivity
    eps0: float = 1.0

    def validate(self) -> None:
        _probability(self, "lam", "eps0")
        _positive(self, "nu")


BMC_OBSERVATIONS = ("per_step", "per_transition")


@dataclass
class BmcConfig:
    alpha0: float = 25.0
    beta0: float = 25.01  # the authors' code; the paper says 25
    a0: float = 250.0
    b0: float = 250.0
    mu0: float = 0.0
    tau0: float = 1.0
    # Which transitions of each batch the posterior observes: "per_step" (the authors' rate:
    # as many per update as env steps per update, the newest step of each trace first) or
    # "per_transition" (every unmasked transition of the batch: 30 per update, 7.5 per env step).
    observations: str = "per_step"

    def validate(self) -> None:
        _positive(self, "alpha0", "beta0", "a0", "b0", "tau0")
        _check(self.observations in BMC_OBSERVATIONS, "observations", f"must be one of {', '.join(BMC_OBSERVATIONS)}")


@dataclass
class SoftmaxConfig:
    kappa: float = 0.1  # temperature

    def validate(self) -> None:
        _positive(self, "kappa")


@dataclass
class MaxBoltzmannConfig:
    epsilon: float = 0.05
    kappa: float = 0.1

    def validate(self) -> None:
        _probability(self, "epsilon")
        _positive(self, "kappa")


@dataclass
class ExplorationConfig:
    strategy: str = "bmc"
    constant: ConstantEpsilonConfig = field(default_factory=ConstantEpsilonConfig)
    decreasing: DecreasingEpsilonConfig = field(default_factory=DecreasingEpsilonConfig)
    vdbe: VdbeConfig = field(default_factory=VdbeConfig)
    bmc: BmcConfig = field(default_factory=BmcConfig)
    softmax: SoftmaxConfig = field(default_factory=SoftmaxConfig)
    max_boltzmann: MaxBoltzmannConfig = field(default_factory=MaxBoltzmannConfig)

    def validate(self) -> None:
        _check(self.strategy in STRATEGIES, "strategy", f"must be one of {', '.join(STRATEGIES)}")


CAMERAS = ("front", "topdown")


@dataclass
class EnvConfig:
    speed: float = 10.0  # m/s, held constant
    max_steer_deg: float = 25.0  # highway-env's bicycle model then turns on a 9.9 m radius
    # Decisions per second. At 10 Hz a step is 1 m of road: random steering then stays on the
    # road for about 19 steps (median 15), enough for traces of 10; at 5 Hz only 7.6 (median 6).
    policy_frequency: int = 10
    # highway-env's motion model (forward Euler) is stepped this often; a multiple of policy_frequency.
    simulation_frequency: int = 20
    reward_beta: float = 0.8  # r = exp(-beta * d), d the distance to the street's centre-line
    offroad_distance: float = 3.7  # m from the centre-line that ends an episode (the kerb)
    max_steps: int = 2000  # a cut, not a terminal state
    lane_offset_m: float = 2.0  # highway-env lanes run this far right of the centre-line, one per direction

    # What the car sees: "front" (a pinhole camera on the roof, the paper's set-up) or
    # "topdown" (a heading-up map crop, nearly fully observed; for comparison).
    camera: str = "front"
    camera_height_m: float = 1.4  # front camera above the road
    camera_pitch_deg: float = 5.0  # front camera tilted down from the horizontal
    camera_hfov_deg: float = 90.0  # front camera's horizontal field of view
    camera_range_m: float = 40.0  # front camera: nothing farther is drawn (haze); 40 m keeps the step fast
    topdown_ahead_m: float = 30.0  # top-down camera: metres of road visible ahead of the car
    topdown_behind_m: float = 2.0
    topdown_width_m: float = 24.0
    render_scale: float = 8.0  # pixels per metre of the pre-drawn world

    # Each start pose is shifted sideways and turned by a uniform draw within these bounds
    # (the env's RNG), so repeated trials from one start differ as AirSim's physics made them.
    start_jitter_m: float = 0.3
    start_jitter_deg: float = 3.0

    # An episode that covers less than stall_min_progress_m of new road in stall_window_s ends
    # as "stalled" (terminated, like leaving the road): circling on a junction is not driving.
    # Road counts as new when not driven within progress_memory_s (shorter than a lap of the
    # smallest block, about 27 s at 10 m/s, so going round a block keeps counting).
    stall_window_s: float = 10.0
    stall_min_progress_m: float = 25.0
    progress_memory_s: float = 20.0

    # Moving traffic (beyond the paper, which had none): highway-env IDM vehicles on routes of
    # their own, at speeds drawn from [traffic_speed_min, traffic_speed_max] m/s.
    traffic_vehicles: int = 0
    traffic_speed_min: float = 6.0
    traffic_speed_max: float = 9.0

    def validate(self) -> None:
        _positive(self, "speed", "max_steer_deg", "policy_frequency", "simulation_frequency",
                  "reward_beta", "offroad_distance", "max_steps", "camera_height_m",
                  "camera_hfov_deg", "camera_range_m", "topdown_ahead_m", "topdown_width_m",
                  "render_scale", "stall_window_s", "progress_memory_s", "traffic_speed_min")
        _check(self.camera in CAMERAS, "camera", f"must be one of {', '.join(CAMERAS)}")
        _check(self.simulation_frequency % self.policy_frequency == 0, "simulation_frequency",
               "must be a multiple of policy_frequency")
        _check(0 <= self.lane_offset_m < self.offroad_distance, "lane_offset_m", "must lie in [0, offroad_distance)")
        _check(self.topdown_behind_m >= 0, "topdown_behind_m", "must be >= 0")
        _check(self.max_steer_deg < 90, "max_steer_deg", "must be < 90")
        _check(-45 < self.camera_pitch_deg < 45, "camera_pitch_deg", "must lie in (-45, 45)")
        _check(self.camera_hfov_deg < 170, "camera_hfov_deg", "must be < 170")
        _check(0 <= self.start_jitter_m < self.offroad_distance, "start_jitter_m", "must lie in [0, offroad_distance)")
        _check(0 <= self.start_jitter_deg < 45, "start_jitter_deg", "must lie in [0, 45)")
        _check(self.stall_min_progress_m >= 0, "stall_min_progress_m", "must be >= 0")
        # 20 cars always found room to start in tests (seeds 0-4); 30 did for only 2 seeds of 5.
        _check(0 <= self.traffic_vehicles <= 20, "traffic_vehicles", "must lie in [0, 20]")
        _check(self.traffic_speed_min <= self.traffic_speed_max, "traffic_speed_max",
               "must be >= traffic_speed_min")


@dataclass
class ActorConfig:
    num_actors: int = 0  # local stack: 0 means one per spare core
    actor_id: int = 0
    log_period_s: float = 10.0
    # Finished episodes wait in a queue while no replay listens (a replay restart); the actor
    # holds its next episode while the queue has this many episodes or this many MB.
    queue_episodes: int = 32
    queue_mb: float = 256.0

    def validate(self) -> None:
        _check(self.num_actors >= 0, "num_actors", "must be >= 0")
        _check(self.actor_id >= 0, "actor_id", "must be >= 0")
        _positive(self, "log_period_s", "queue_episodes", "queue_mb")


@dataclass
class EvaluationConfig:
    episodes_per_start: int = 30
    max_steps: int = 2000
    workers: int = 2
    envs_per_worker: int = 4
    reward_bins: list[float] = field(default_factory=lambda: [0.0, 0.25, 0.5, 0.75, 1.0])
    seed: int = 0  # root of every trial's seed (env reset, random baseline, privileged driver's turns)
    progress_period_s: float = 1.0  # how often the progress line on stderr is refreshed
    live_timeout_s: float = 30.0  # --live: how long to wait for the learner's latest weights
    # Intervals of the tables: stratified bootstrap over runs and trials (actor/evaluation/intervals.py).
    bootstrap_replicates: int = 2000
    confidence: float = 0.95

    def validate(self) -> None:
        _positive(self, "episodes_per_start", "max_steps", "workers", "envs_per_worker",
                  "progress_period_s", "live_timeout_s", "bootstrap_replicates")
        _check(self.seed >= 0, "seed", "must be >= 0")
        _check(0.0 < self.confidence < 1.0, "confidence", "must lie in (0, 1)")
        bins = self.reward_bins
        _check(len(bins) >= 2 and all(a < b for a, b in zip(bins, bins[1:])), "reward_bins", "must be at least two increasing edges")


@dataclass
class TransportConfig:
    mode: str = "peer"  # "peer", "client" or "router"
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    multicast_scouting: bool = False
    namespace: str = "d3rqn"
    connect_timeout_s: float = 10.0  # client mode: how long opening a session retries its connect endpoints
    # TLS on tls/<host>:<port> endpoints (README "Securing a cluster"; d3rqn-certs makes the files).
    # PEM files; relative paths start from the working directory.
    tls_ca: str = ""  # the run's CA: listeners' certificates (and with tls_mtls, peers') must be signed by it
    tls_certificate: str = ""  # this host's certificate, shown when listening (and with tls_mtls, connecting)
    tls_key: str = ""  # its private key
    tls_mtls: bool = False  # mutual TLS: listeners admit only peers with a certificate signed by tls_ca
    tls_verify_name: bool = True  # a connecting process checks the listener's certificate names the address dialled
    # Access control on this session's links (the router's), by the common name of each peer's
    # certificate (needs tls_mtls; common/access.py lists what each role may do). Deny by default.
    acl: bool = False
    acl_learners: list[str] = field(default_factory=lambda: ["learner"])
    acl_actors: list[str] = field(default_factory=lambda: ["actor"])
    acl_replays: list[str] = field(default_factory=lambda: ["replay"])  # a replay that is not the router
    acl_observers: list[str] = field(default_factory=lambda: ["recorder"])  # read everything, write nothing

    def validate(self) -> None:
        _check(self.mode in ("peer", "client", "router"), "mode", "must be 'peer', 'client' or 'router'")
        _positive(self, "connect_timeout_s")
        for key in ("listen", "connect"):
            for endpoint in getattr(self, key):
                _check("/" in endpoint, key, f"endpoint {endpoint!r} must look like 'tcp/127.0.0.1:7447'")
        _check(_is_key_chunk(self.namespace), "namespace", "must be a non-empty key chunk without '/', '*', '$', '?' or '#'")
        self._validate_security()

    def _validate_security(self) -> None:
        _check(bool(self.tls_certificate) == bool(self.tls_key), "tls_key",
               "tls_certificate and tls_key go together: give both or neither")
        if any(endpoint.startswith("tls/") for endpoint in self.listen):
            _check(bool(self.tls_certificate), "tls_certificate", "a tls/ listener needs a certificate and key")
        if any(endpoint.startswith("tls/") for endpoint in self.listen + self.connect):
            _check(bool(self.tls_ca), "tls_ca", "tls/ endpoints need the run's CA certificate")
        if self.tls_mtls:
            _check(bool(self.tls_certificate and self.tls_ca), "tls_mtls", "needs tls_ca, tls_certificate and tls_key")
            for key in ("listen", "connect"):
                for endpoint in getattr(self, key):
                    _check(endpoint.startswith("tls/"), key,
                           f"endpoint {endpoint!r}: with tls_mtls every endpoint must be tls/ (another would admit peers without a certificate)")
        if self.acl:
            _check(self.tls_mtls, "acl", "needs tls_mtls: the access rules tell peers apart by their certificates")
        for key in ("acl_learners", "acl_actors", "acl_replays", "acl_observers"):
            for name in getattr(self, key):
                _check(bool(name.strip()), key, "common names must not be empty")


@dataclass
class RunConfig:
    name: str = "default"
    seed: int = 0
    runs_dir: str = "runs"

    def validate(self) -> None:
        _check(_is_key_chunk(self.name), "name", "must be a non-empty key chunk without '/', '*', '$', '?' or '#'")


@dataclass
class RecorderConfig:
    """The flight recorder (replay/log): what it keeps of a run's traffic and how it writes the MCAP file."""

    enabled: bool = True  # the local stack starts a recorder writing <runs_dir>/<run>/traffic.mcap
    # A Weights message is 48 MB: keep one when its version is this far past the last kept one
    # (the first and the last of a run are always kept); a paper run has ~250,000 versions.
    weights_every_versions: int = 50_000
    flush_period_s: float = 5.0  # closes the open chunk this often: a killed recorder loses at most this span
    chunk_mb: float = 4.0  # a chunk also closes at this size
    queue_messages: int = 10_000  # hand-off from Zenoh's threads to the writer; beyond it messages are
    queue_mb: float = 512.0  # dropped and counted, never waited for
    views: bool = True  # JSON copies of metrics, stats and exploration state that Foxglove reads without plugins
    images: bool = False  # camera frames as foxglove.CompressedImage while recording (CPU, size); see `export --images`
    image_format: str = "png"  # "png" (lossless) or "jpeg"
    stats_period_s: float = 5.0  # the recorder's own counters on metrics/recorder/0

    def validate(self) -> None:
        _positive(self, "weights_every_versions", "flush_period_s", "chunk_mb", "queue_messages", "queue_mb",
                  "stats_period_s")
        _check(self.image_format in ("png", "jpeg"), "image_format", "must be 'png' or 'jpeg'")


@dataclass
class Config:
    run: RunConfig = field(default_factory=RunConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    replay: ReplayConfig = field(default_factory=ReplayConfig)
    learner: LearnerConfig = field(default_factory=LearnerConfig)
    exploration: ExplorationConfig = field(default_factory=ExplorationConfig)
    env: EnvConfig = field(default_factory=EnvConfig)
    actor: ActorConfig = field(default_factory=ActorConfig)
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)
    transport: TransportConfig = field(default_factory=TransportConfig)
    record: RecorderConfig = field(default_factory=RecorderConfig)

    def validate(self) -> "Config":
        for path, section in _sections(self):
            if section is self:
                continue
            try:
                section.validate()
            except ConfigError as error:
                raise ConfigError(f"{path}.{error}" if path else str(error)) from None
        _check(self.learner.start_episodes <= self.replay.capacity, "learner.start_episodes",
               f"{self.learner.start_episodes} exceeds replay.capacity {self.replay.capacity}: updates would never start")
        return self


# --- presets -----------------------------------------------------------------

PRESETS: dict[str, dict[str, Any]] = {
    # The paper's values are the dataclass defaults.
    "paper": {},
    # The main job on a 2-core CPU machine (about 30 minutes): the paper's agent, buffer and
    # ratio, with the run cut to 60,000 steps and the decreasing schedule scaled to that length.
    "local": {
        "learner.total_env_steps": 60_000,
        "learner.start_steps": 10_000,
        "learner.checkpoint_every": 1_000,
        "exploration.decreasing.n_start": 10_000,
        "exploration.decreasing.n_ann": 20_000,
        "exploration.decreasing.n_max": 60_000,
    },
    # Seconds-long runs for tests: tiny buffer, short episodes, early updates.
    "smoke": {
        "replay.capacity": 50,
        "replay.stats_period_s": 0.5,
        "replay.error_buffer_updates": 2.0,  # short runs: the run's ratio within 2 updates
        "learner.batch_size": 4,
        "learner.env_steps_per_update": 20.0,  # the random phase's backlog clears in seconds
        "learner.start_episodes": 2,
        "learner.start_steps": 100,
        "learner.total_env_steps": 20_000,
        "learner.weights_every": 5,
        "learner.checkpoint_every": 50,
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
    },
}


# --- building a config ---------------------------------------------------------

def load_config(preset: str = "paper", toml_path: str | Path | None = None,
                overrides: dict[str, Any] | None = None, base: Config | None = None) -> Config:
    """Preset (or a copy of `base`, such as a checkpoint's config), then TOML file, then
    overrides (dotted keys); validated."""
    if base is not None:
        config = copy.deepcopy(base)
    elif preset in PRESETS:
        config = Config()
        for key, value in PRESETS[preset].items():
            set_value(config, key, value)
    else:
        raise ConfigError(f"preset: unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    if toml_path is not None:
        for key, value in _flatten(_read_toml(Path(toml_path))).items():
            set_value(config, key, value)
    for key, value in (overrides or {}).items():
        set_value(config, key, value)
    return config.validate()


# Keys of earlier versions; a checkpoint's or log's config that holds one still loads (from_dict).
RETIRED_KEYS = {
    "learner.ratio_tolerance": "replaced by replay.error_buffer_updates (a number of updates)",
    "actor.pace_with_learner": "the replay's rate limiter paces the actors; replay.error_buffer_updates 1e9 lets them run free",
}


def set_value(config: Config, dotted_key: str, value: Any) -> None:
    """Set one field by its dotted path, converting and type-checking the value."""
    if dotted_key in RETIRED_KEYS:
        raise ConfigError(f"{dotted_key}: retired key; {RETIRED_KEYS[dotted_key]}")
    *parents, name = dotted_key.split(".")
    target: Any = config
    for part in parents:
        if not dataclasses.is_dataclass(target) or part not in _field_types(target):
            raise ConfigError(f"{dotted_key}: unknown key")
        target = getattr(target, part)
    types = _field_types(target) if dataclasses.is_dataclass(target) else {}
    if name not in types or dataclasses.is_dataclass(types[name]):
        raise ConfigError(f"{dotted_key}: unknown key")
    setattr(target, name, _coerce(dotted_key, types[name], value))


def flat_items(config: Any, prefix: str = "") -> dict[str, Any]:
    """Every leaf field as {dotted key: value}."""
    items: dict[str, Any] = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        key = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(value):
            items.update(flat_items(value, key + "."))
        else:
            items[key] = value
    return items


def to_toml(config: Config) -> str:
    """The config as a TOML document that load_config reads back unchanged."""
    lines: list[str] = []
    for path, section in _sections(config):
        leaves = {f.name: getattr(section, f.name) for f in dataclasses.fields(section)
                  if not dataclasses.is_dataclass(getattr(section, f.name))}
        if not path or not leaves:
            continue
        lines.append(f"[{path}]")
        lines.extend(f"{name} = {_toml_value(value)}" for name, value in leaves.items())
        lines.append("")
    return "\n".join(lines)


def from_dict(nested: dict[str, Any]) -> Config:
    """A config from the nested dict of a TOML document or a checkpoint."""
    config = Config()
    for key, value in _flatten(nested).items():
        if key not in RETIRED_KEYS:
            set_value(config, key, value)
    return config.validate()


def to_dict(config: Config) -> dict[str, Any]:
    return dataclasses.asdict(config)


# --- command line ------------------------------------------------------------------

def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """Adds --preset, --config, --dump-config and one flag per config field."""
    parser.add_argument("--preset", default="paper", choices=sorted(PRESETS), help="base values (default: paper)")
    parser.add_argument("--config", metavar="FILE.toml", help="TOML file applied over the preset")
    parser.add_argument("--dump-config", action="store_true", help="print the resolved config as TOML and exit")
    defaults = flat_items(Config())
    group = parser.add_argument_group("configuration (dotted keys; applied over preset and file)")
    for key, default in defaults.items():
        shown = _toml_value(default)
        group.add_argument(f"--{key}", dest=_dest(key), default=None, metavar=_metavar(default),
                           help=f"default {shown}")


def config_from_args(args: argparse.Namespace, base: Config | None = None) -> Config:
    """The flags of add_config_arguments applied over the preset, or over `base` if given."""
    overrides = {key: getattr(args, _dest(key)) for key in flat_items(Config())
                 if getattr(args, _dest(key), None) is not None}
    return load_config(args.preset, args.config, overrides, base)


def parse_config_or_exit(parser: argparse.ArgumentParser, argv: list[str] | None = None
                         ) -> tuple[argparse.Namespace, Config]:
    """Parses argv; a config error is one line on stderr and exit code 2, not a traceback.

    With --dump-config, prints the TOML and exits 0.
    """
    args = parser.parse_args(argv)
    try:
        config = config_from_args(args)
    except ConfigError as error:
        print(f"{parser.prog}: config error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    if args.dump_config:
        print(to_toml(config), end="")
        raise SystemExit(0)
    return args, config


def print_config(prog: str, config: Config) -> None:
    """The resolved config on stderr, so every process's log starts with what it ran with."""
    body = "\n".join(f"  {line}" for line in to_toml(config).splitlines() if line)
    print(f"{prog}: resolved config\n{body}", file=sys.stderr, flush=True)


# --- helpers -------------------------------------------------------------------------

def _sections(config: Any, path: str = ""):
    yield path, config
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            yield from _sections(value, f"{path}.{f.name}" if path else f.name)


def _field_types(instance: Any) -> dict[str, Any]:
    return typing.get_type_hints(type(instance))


def _coerce(key: str, kind: Any, value: Any) -> Any:
    origin = typing.get_origin(kind)
    if origin is list:
        (item_kind,) = typing.get_args(kind)
        if isinstance(value, str):
            value = [part for part in (p.strip() for p in value.split(",")) if part]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        return [_coerce(key, item_kind, item) for item in value]
    if kind is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "1", "yes", "on", "false", "0", "no", "off"):
            return value.lower() in ("true", "1", "yes", "on")
        raise ConfigError(f"{key}: expected true or false, got {value!r}")
    if kind is int:
        if isinstance(value, bool):
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        if isinstance(value, int):
            return value
        if isinstance(value, str):
            try:
                return int(value.replace("_", ""))
            except ValueError:
                pass
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise ConfigError(f"{key}: expected an integer, got {value!r}")
    if kind is float:
        if isinstance(value, bool):
            raise ConfigError(f"{key}: expected a number, got {value!r}")
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise ConfigError(f"{key}: expected a number, got {value!r}") from None
        if not math.isfinite(number):
            raise ConfigError(f"{key}: expected a finite number, got {value!r}")
        return number
    if kind is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: expected a string, got {value!r}")
        return value
    raise ConfigError(f"{key}: unsupported field type {kind!r}")


def _flatten(nested: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in nested.items():
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _read_toml(path: Path) -> dict[str, Any]:
    try:
        with path.open("rb") as handle:
            return tomllib.load(handle)
    except FileNotFoundError:
        raise ConfigError(f"config file {path}: not found") from None
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"config file {path}: invalid TOML ({error})") from None


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(item) for item in value) + "]"
    raise TypeError(f"cannot write {value!r} as TOML")


def _dest(key: str) -> str:
    return "cfg__" + key.replace(".", "__")


def _metavar(default: Any) -> str:
    if isinstance(default, bool):
        return "BOOL"
    if isinstance(default, int):
        return "INT"
    if isinstance(default, float):
        return "FLOAT"
    if isinstance(default, list):
        return "A,B,..."
    return "STR"


def _check(condition: bool, key: str, message: str) -> None:
    if not condition:
        raise ConfigError(f"{key}: {message}")


def _positive(section: Any, *names: str) -> None:
    for name in names:
        value = getattr(section, name)
        _check(value > 0, name, f"must be > 0, got {value!r}")


def _probability(section: Any, *names: str) -> None:
    for name in names:
        value = getattr(section, name)
        _check(0.0 <= value <= 1.0, name, f"must lie in [0, 1], got {value!r}")


def _is_key_chunk(text: str) -> bool:
    return bool(text) and not any(char in text for char in "/*$?# ")
