"""The simulated drive's and the evaluation's config sections (env, evaluation), apart from the learner's
and the services' in common/config.py, which assembles them into the one Config."""

from __future__ import annotations

from dataclasses import dataclass

from common.schema.fields import check, check_positive, option

CAMERAS = ("front", "topdown")


@dataclass
class EnvConfig:
    """The simulated drive (actor/sim/): the car, the reward, the camera, episode ends, traffic."""

    speed: float = option(10.0, "the car's speed, held constant", "m/s")
    max_steer_deg: float = option(25.0, "largest steering angle; highway-env's bicycle model then turns on a 9.9 m "
                                        "radius", "degrees")
    policy_frequency: int = option(10, "decisions per second. At 10 Hz a step is 1 m of road: random steering then "
                                       "stays on the road for about 19 steps (median 15), enough for traces of 10; "
                                       "at 5 Hz only 7.6 (median 6)", "Hz")
    simulation_frequency: int = option(20, "how often highway-env's motion model (forward Euler) is stepped; a "
                                           "multiple of policy_frequency", "Hz")
    reward_beta: float = option(0.8, "beta of the reward r = exp(-beta * d), d the distance to the street's "
                                     "centre-line", "1/m")
    offroad_distance: float = option(3.7, "distance from the centre-line that ends an episode (the kerb)", "m")
    max_steps: int = option(2000, "an episode is cut here (a cut, not a terminal state)", "steps")
    lane_offset_m: float = option(2.0, "highway-env lanes run this far right of the centre-line, one per direction",
                                  "m")
    camera: str = option("front", "what the car sees: front (a pinhole camera on the roof, the paper's set-up) or "
                                  "topdown (a heading-up map crop, nearly fully observed; for comparison)",
                         choices=CAMERAS)
    camera_height_m: float = option(1.4, "front camera's height above the road", "m")
    camera_pitch_deg: float = option(5.0, "front camera's tilt down from the horizontal", "degrees")
    camera_hfov_deg: float = option(90.0, "front camera's horizontal field of view", "degrees")
    camera_range_m: float = option(40.0, "front camera: nothing farther is drawn (haze); 40 m keeps the step fast",
                                   "m")
    topdown_ahead_m: float = option(30.0, "top-down camera: road visible ahead of the car", "m")
    topdown_behind_m: float = option(2.0, "top-down camera: road visible behind the car", "m")
    topdown_width_m: float = option(24.0, "top-down camera: width of the road visible", "m")
    render_scale: float = option(8.0, "resolution of the pre-drawn world", "px/m")
    # Uniform draws from the env's RNG, so repeated trials from one start differ as AirSim's physics made them.
    start_jitter_m: float = option(0.3, "each start pose is shifted sideways by a uniform draw within +-this", "m")
    start_jitter_deg: float = option(3.0, "each start pose is turned by a uniform draw within +-this", "degrees")
    # Circling on a junction is not driving.
    stall_window_s: float = option(10.0, "an episode that covers less than stall_min_progress_m of new road in this "
                                         "time ends as stalled (terminated, like leaving the road)", "s")
    stall_min_progress_m: float = option(25.0, "new road an episode must cover in each stall_window_s", "m")
    progress_memory_s: float = option(20.0, "road counts as new when not driven within this time (shorter than a "
                                            "lap of the smallest block, about 27 s at 10 m/s, so going round a block "
                                            "keeps counting)", "s")
    traffic_vehicles: int = option(0, "moving traffic (beyond the paper, which had none): highway-env IDM vehicles "
                                      "on routes of their own, at most 20", "vehicles")
    traffic_speed_min: float = option(6.0, "slowest speed a traffic vehicle is given (drawn uniformly)", "m/s")
    traffic_speed_max: float = option(9.0, "fastest speed a traffic vehicle is given (drawn uniformly)", "m/s")

    def validate(self) -> None:
        check_positive(self, "speed", "max_steer_deg", "policy_frequency", "simulation_frequency",
                       "reward_beta", "offroad_distance", "max_steps", "camera_height_m",
                       "camera_hfov_deg", "camera_range_m", "topdown_ahead_m", "topdown_width_m",
                       "render_scale", "stall_window_s", "progress_memory_s", "traffic_speed_min")
        check(self.camera in CAMERAS, "camera", f"must be one of {', '.join(CAMERAS)}")
        check(self.simulation_frequency % self.policy_frequency == 0, "simulation_frequency",
              "must be a multiple of policy_frequency")
        check(0 <= self.lane_offset_m < self.offroad_distance, "lane_offset_m", "must lie in [0, offroad_distance)")
        check(self.topdown_behind_m >= 0, "topdown_behind_m", "must be >= 0")
        check(self.max_steer_deg < 90, "max_steer_deg", "must be < 90")
        check(-45 < self.camera_pitch_deg < 45, "camera_pitch_deg", "must lie in (-45, 45)")
        check(self.camera_hfov_deg < 170, "camera_hfov_deg", "must be < 170")
        check(0 <= self.start_jitter_m < self.offroad_distance, "start_jitter_m", "must lie in [0, offroad_distance)")
        check(0 <= self.start_jitter_deg < 45, "start_jitter_deg", "must lie in [0, 45)")
        check(self.stall_min_progress_m >= 0, "stall_min_progress_m", "must be >= 0")
        # 20 cars always found room to start in tests (seeds 0-4); 30 did for only 2 seeds of 5.
        check(0 <= self.traffic_vehicles <= 20, "traffic_vehicles", "must lie in [0, 20]")
        check(self.traffic_speed_min <= self.traffic_speed_max, "traffic_speed_max",
              "must be >= traffic_speed_min")


@dataclass
class EvaluationConfig:
    """`evaluate`: greedy episodes from every start pose, and the intervals of the tables."""

    episodes_per_start: int = option(30, "episodes from each start pose of each start set", "episodes")
    max_steps: int = option(2000, "an evaluation episode is cut here", "steps")
    workers: int = option(2, "evaluation processes", "processes")
    envs_per_worker: int = option(
        64, "simulators each worker steps in lockstep with one batched forward pass (fewer when its share of the "
            "jobs is smaller): a pass reads the LSTM's 44 MB of input weights whatever the batch, so 4 made a third "
            "to a half of the batched actor's env steps per core and 64 as many (busy 2-core AMD EPYC, "
            "deploy/bench/evaluation_speed.py)", "simulators")
    torch_threads: int = option(0, "torch threads per worker; 0: the cores divided among the workers, or 1 with "
                                   "--follow: beside a training run a worker's second thread waits on a busy core "
                                   "(a forward pass ran 8x slower on 2 threads than on 1, busy 2-core AMD EPYC)",
                                "threads")
    reward_bins: list[float] = option([0.0, 0.25, 0.5, 0.75, 1.0], "edges of the bins the episodes' step rewards "
                                                                   "are counted in; must cover [0, 1]")
    seed: int = option(0, "root of every trial's seed (env reset, random baseline, privileged driver's turns) and "
                          "of the bootstrap")
    progress_period_s: float = option(1.0, "how often the status line on stderr is refreshed on a terminal", "s")
    progress_log_period_s: float = option(30.0, "how often a status line is written when stderr is a file or a "
                                                "pipe (a log), not a terminal", "s")
    live_timeout_s: float = option(30.0, "--live: how long to wait for the learner's latest weights", "s")
    bootstrap_replicates: int = option(2000, "replicates of the tables' intervals: a stratified bootstrap over "
                                             "runs and trials (common/analysis/intervals.py)", "replicates")
    confidence: float = option(0.95, "level of the tables' percentile intervals, in (0, 1)")

    def validate(self) -> None:
        check_positive(self, "episodes_per_start", "max_steps", "workers", "envs_per_worker",
                       "progress_period_s", "progress_log_period_s", "live_timeout_s", "bootstrap_replicates")
        check(self.seed >= 0, "seed", "must be >= 0")
        check(self.torch_threads >= 0, "torch_threads", "must be >= 0 (0: the cores divided among the workers)")
        check(0.0 < self.confidence < 1.0, "confidence", "must lie in (0, 1)")
        bins = self.reward_bins
        check(len(bins) >= 2 and all(a < b for a, b in zip(bins, bins[1:])), "reward_bins", "must be at least two increasing edges")
