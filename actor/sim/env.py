"""The driving simulator: a highway-env ``AbstractEnv`` of a small urban neighbourhood.

The car holds a constant speed and only steers (five discrete angles); it sees
through a front camera; its reward is exp(-beta * d) with d its distance to
the nearest street centre-line, 0 on a collision. An episode ends
(``terminated``) on a collision with a parked car, tree, house or traffic
vehicle, on leaving the road (d > ``offroad_distance``) or on stalling (too
little new road in a window, see ``progress.py``); it is cut (``truncated``)
at ``max_steps``. ``info["end"]`` says which: "collision", "offroad",
"stalled" or "cap"; ``info["hit"]`` names what a collision touched
(``collision_site.py``) and ``info["pose"]`` is the car's (x, y, heading).

What is highway-env's and what is ours:

* highway-env's: the ``Road`` and its ``RoadNetwork`` (a connected two-way lane
  graph, ``road.py``), the ego car (a ``Vehicle`` whose own ``step`` is the
  motion model, ``vehicles.py``), the traffic (``IDMVehicle`` subclasses,
  ``traffic.py``), the ``ObservationType``/``ActionType`` plumbing, so
  highway-env's observations (Kinematics, OccupancyGrid, TimeToCollision, its
  grey-scale renderer) run on this env.
* ours: the step loop. ``AbstractEnv.step`` would also test every vehicle
  against every object with Python polygon code at every simulation frame,
  far beyond the step budget; instead the ego car is tested against arrays of
  the same geometry in one vectorised query (``geometry.py``), and its
  distance to the centre-line comes from the same pass that measures its
  progress. ``reset`` is ours too, so that the spaces are built once and keep
  their seeds across episodes.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from highway_env import utils
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.envs.common.action import ActionType, action_factory
from highway_env.envs.common.observation import ObservationType, observation_factory

from actor.sim import layout
from actor.sim.camera import FRAME_SHAPE, TopDownCamera
from actor.sim.front_camera import PerspectiveCamera
from actor.sim.collision_site import touched
from actor.sim.geometry import NO_CIRCLES, Obstacles
from actor.sim.neighbourhood import Pose, neighbourhood, places_reached
from actor.sim.progress import ProgressMeter
from actor.sim.road import lane_locator, neighbourhood_road
from actor.sim.vehicles import EgoVehicle
from actor.sim.world_image import ground_image, world_image
from common.sim_config import EnvConfig
from common.schema.fields import ConfigError

STEERING_LEVELS = (-1.0, -0.5, 0.0, 0.5, 1.0)  # times the maximum angle; positive turns right
START_SETS = ("train", "test")
OPTION_KEYS = ("start_set", "start_index")
END_REASONS = ("collision", "offroad", "stalled", "cap")
CAMERA_OBSERVATIONS = {"front": "FrontCamera", "topdown": "TopDownCamera"}


class SteeringAction(ActionType):
    """``Discrete(5)``: steering angle = level x maximum angle; the speed never changes."""

    def __init__(self, env: AbstractEnv, max_steering: float, **kwargs: Any) -> None:
        super().__init__(env)
        self.max_steering = max_steering

    def space(self) -> spaces.Discrete:
        return spaces.Discrete(len(STEERING_LEVELS))

    @property
    def vehicle_class(self) -> type:
        return EgoVehicle

    def steering(self, action: Any) -> float:
        """The steering angle in radians of an action index; a clear error for anything else."""
        if isinstance(action, np.ndarray) and action.shape == ():
            action = action.item()
        if isinstance(action, (bool, np.bool_)) or not isinstance(action, (int, np.integer)) \
                or not 0 <= action < len(STEERING_LEVELS):
            raise ConfigError(f"action: must be an integer in [0, {len(STEERING_LEVELS)}), got {action!r}")
        return STEERING_LEVELS[int(action)] * self.max_steering

    def act(self, action: Any) -> None:
        self.controlled_vehicle.act({"steering": self.steering(action), "acceleration": 0.0})


class CameraObservation(ObservationType):
    """One of the env's cameras: uint8 RGB, shape (66, 200, 3)."""

    def __init__(self, env: AbstractEnv, camera: str, **kwargs: Any) -> None:
        super().__init__(env)
        self.camera = camera

    def space(self) -> spaces.Box:
        return spaces.Box(low=0, high=255, shape=FRAME_SHAPE, dtype=np.uint8)

    def observe(self) -> np.ndarray:
        return self.env.cameras(self.camera).frame(*self.env.pose, self.env.traffic_rectangles())


class NeighbourhoodEnv(AbstractEnv):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, env_config: EnvConfig | None = None, render_mode: str | None = None,
                 observation: dict | None = None, action: dict | None = None) -> None:
        """``observation`` / ``action``: a highway-env observation or action config that
        replaces the camera or the five steering levels (benchmarks, tools)."""
        self.env_config = env_config if env_config is not None else EnvConfig()
        self.env_config.validate()
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ConfigError(f"render_mode: must be one of {self.metadata['render_modes']} or None")
        self.hood = neighbourhood()
        self._cameras: dict[str, Any] = {}
        self.pose = (0.0, 0.0, 0.0)
        self.start_set, self.start_index = START_SETS[0], 0
        self.distance, self.collision, self.stalled, self.hit = 0.0, False, False, ""
        self.place_name, self.streets_visited = "", set()
        self.traffic = None
        config = self.env_config
        self.metadata = {**self.metadata, "render_fps": config.policy_frequency}
        self.progress = ProgressMeter(self.hood.centre_lines,
                                      memory_steps=round(config.progress_memory_s * config.policy_frequency),
                                      window_steps=round(config.stall_window_s * config.policy_frequency),
                                      min_progress_m=config.stall_min_progress_m,
                                      step_m=config.speed / config.policy_frequency)
        super().__init__({"observation": observation or {"type": CAMERA_OBSERVATIONS[config.camera]},
                          "action": action or {"type": "SteeringAction"},
                          "policy_frequency": config.policy_frequency,
                          "simulation_frequency": config.simulation_frequency}, render_mode)

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        utils.update_config(config, {"observation": {"type": "FrontCamera"},
                                     "action": {"type": "SteeringAction"}})
        return config

    def define_spaces(self) -> None:
        observation, action = self.config["observation"], self.config["action"]
        cameras = {name: key for key, name in CAMERA_OBSERVATIONS.items()}
        if observation["type"] in cameras:
            self.observation_type = CameraObservation(self, cameras[observation["type"]])
        else:
            self.observation_type = observation_factory(self, observation)
        if action["type"] == "SteeringAction":
            self.action_type = SteeringAction(self, math.radians(self.env_config.max_steer_deg))
        else:
            self.action_type = action_factory(self, action)
        self.observation_space = self.observation_type.space()
        self.action_space = self.action_type.space()

    def cameras(self, name: str):
        """The env's camera called ``name`` ("front" or "topdown"), built on first use."""
        if name not in self._cameras:
            self._cameras[name] = self._build_camera(name)
        return self._cameras[name]

    def _build_camera(self, name: str):
        config = self.env_config
        if name == "topdown":
            return TopDownCamera(world_image(config.render_scale, config.offroad_distance),
                                 config.topdown_ahead_m, config.topdown_behind_m, config.topdown_width_m)
        return PerspectiveCamera(ground_image(config.render_scale, config.offroad_distance), self.hood,
                                 height_m=config.camera_height_m, pitch_deg=config.camera_pitch_deg,
                                 hfov_deg=config.camera_hfov_deg, range_m=config.camera_range_m)

    # --- episode ---------------------------------------------------------------------------

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        """``options``: ``start_set`` ("train" by default, or "test") and ``start_index``
        (drawn from the set with the env's RNG when absent)."""
        gym.Env.reset(self, seed=seed)
        self.start_set, self.start_index = self._start(options or {})
        self.time = self.steps = 0
        self.done = False
        self._reset()
        observation = self.observation_type.observe()
        return observation, self._info()

    def _start(self, options: dict) -> tuple[str, int]:
        unknown = sorted(set(options) - set(OPTION_KEYS))
        if unknown:
            raise ConfigError(f"reset options: unknown key(s) {unknown}; known: {list(OPTION_KEYS)}")
        start_set = options.get("start_set", START_SETS[0])
        if start_set not in START_SETS:
            raise ConfigError(f"start_set: must be one of {list(START_SETS)}, got {start_set!r}")
        count = len(self.hood.start_poses[start_set])
        if "start_index" not in options:
            return start_set, int(self.np_random.integers(count))
        index = options["start_index"]
        if isinstance(index, (bool, np.bool_)) or not isinstance(index, (int, np.integer)) \
                or not 0 <= index < count:
            raise ConfigError(f"start_index: must be an integer in [0, {count}), got {index!r}")
        return start_set, int(index)

    def _reset(self) -> None:
        if self.road is None:
            self._build_road()
        start: Pose = self.hood.start_poses[self.start_set][self.start_index]
        self.vehicle.crashed = False
        self.vehicle.speed = self.env_config.speed
        self.vehicle.action = {"steering": 0.0, "acceleration": 0.0}
        self.vehicle.history.clear()
        self.vehicle.place = None
        self._move_to(*self._jittered(start))
        self.progress.reset(self.segment, self.along)
        self.streets_visited = set()
        self._visit(None)
        self.stalled = False
        if self.traffic is not None:
            self.traffic.reset(self.np_random)
            self._collided()

    def _build_road(self) -> None:
        config = self.env_config
        offset, width = config.lane_offset_m, 2 * (config.offroad_distance - config.lane_offset_m)
        self.road = neighbourhood_road(self.hood, offset, width)
        start = self.hood.start_poses[START_SETS[0]][0]
        self.vehicle = EgoVehicle(self.road, [start.x, start.y], start.heading, config.speed)
        self.vehicle.locator = lane_locator(self.hood, self.road.network, offset, width)
        self.road.vehicles.append(self.vehicle)
        if config.traffic_vehicles:
            from actor.sim.traffic import Traffic
            self.traffic = Traffic(self.road, config, self.vehicle)

    def _jittered(self, start: Pose) -> tuple[float, float, float]:
        """The start pose moved sideways and turned by uniform draws within the configured bounds."""
        if self.env_config.start_jitter_m == 0 and self.env_config.start_jitter_deg == 0:
            return start.x, start.y, start.heading
        shift = self.np_random.uniform(-1.0, 1.0) * self.env_config.start_jitter_m
        turn = math.radians(self.np_random.uniform(-1.0, 1.0) * self.env_config.start_jitter_deg)
        sideways_x, sideways_y = -math.sin(start.heading), math.cos(start.heading)
        return start.x + shift * sideways_x, start.y + shift * sideways_y, _wrap_angle(start.heading + turn)

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        if self.road is None:
            raise ConfigError("step: call reset() first")
        self.action_type.act(action)
        frames = self.env_config.simulation_frequency // self.env_config.policy_frequency
        dt = 1.0 / self.env_config.simulation_frequency
        for _ in range(frames):
            if self.traffic is not None:
                self.traffic.act()
                self.traffic.step(dt)
            self.vehicle.step(dt)
            if self._collided():  # a frame's contact counts even if the car moves on
                break
        self.vehicle.refresh_lane()
        before = self.place_name
        self._locate()
        self.steps += 1
        self.time += 1.0 / self.env_config.policy_frequency
        self.progress.update(self.segment, self.along)
        self._visit(before)
        self.stalled = self.progress.stalled
        observation = self.observation_type.observe()
        return (observation, self._reward(), self._is_terminated(), self._is_truncated(), self._info())

    def place(self, x: float, y: float, heading: float) -> np.ndarray:
        """Puts the car at a pose in the current episode (tests, pictures); returns the observation."""
        if self.road is None:
            raise ConfigError("place: call reset() first")
        self._move_to(float(x), float(y), _wrap_angle(float(heading)))
        return self.observation_type.observe()

    def _move_to(self, x: float, y: float, heading: float) -> None:
        self.vehicle.position = np.array([x, y], dtype=np.float64)
        self.vehicle.heading = heading
        self.vehicle.refresh_lane()
        self._collided()
        self._locate()

    def _locate(self) -> None:
        """The nearest centre-line of the pose ``_collided`` took last."""
        x, y, _ = self.pose
        self.segment, self.along, self.distance = self.hood.centre_lines.nearest(x, y)
        self.place_name = self.hood.centre_line_places[self.segment]

    def _visit(self, before: str | None) -> None:
        """Adds the places this step reached (neighbourhood.places_reached) to the episode's: a place
        counts once the car is on it farther than offroad_distance, the most it can be off its line,
        from both its ends; a junction also when the car crosses it from street to street."""
        self.streets_visited.update(places_reached(self.hood, self.segment, self.along,
                                                   self.env_config.offroad_distance, before))

    def _collided(self) -> bool:
        """Takes the ego car's pose and tests it against every obstacle and traffic vehicle."""
        x, y = float(self.vehicle.position[0]), float(self.vehicle.position[1])
        heading = _wrap_angle(float(self.vehicle.heading))
        self.vehicle.heading = heading
        self.pose = (x, y, heading)
        self.collision = self.hood.obstacles.hits(x, y, heading, layout.CAR_LENGTH_M, layout.CAR_WIDTH_M) \
            or self._hits_traffic(x, y, heading)
        self.hit = touched(self.hood, self.pose, self.traffic_rectangles()) if self.collision else ""
        self.vehicle.crashed = self.collision
        return self.collision

    def _hits_traffic(self, x: float, y: float, heading: float) -> bool:
        rectangles = self.traffic_rectangles()
        if rectangles is None or not len(rectangles):
            return False
        reach = np.hypot(rectangles[:, 3], rectangles[:, 4]) / 2 + math.hypot(layout.CAR_LENGTH_M, layout.CAR_WIDTH_M) / 2
        near = (rectangles[:, 0] - x) ** 2 + (rectangles[:, 1] - y) ** 2 <= reach ** 2
        if not near.any():
            return False
        return Obstacles(rectangles[near], NO_CIRCLES).hits(x, y, heading, layout.CAR_LENGTH_M, layout.CAR_WIDTH_M)

    def traffic_rectangles(self) -> np.ndarray | None:
        """The traffic vehicles as rows (x, y, heading, length, width), or None without traffic."""
        return None if self.traffic is None else self.traffic.rectangles()

    # --- reward, ends, info --------------------------------------------------------------------

    @property
    def offroad(self) -> bool:
        return self.distance > self.env_config.offroad_distance

    def _reward(self) -> float:
        return 0.0 if self.collision else math.exp(-self.env_config.reward_beta * self.distance)

    def _is_terminated(self) -> bool:
        return self.collision or self.offroad or self.stalled

    def _is_truncated(self) -> bool:
        return not self._is_terminated() and self.steps >= self.env_config.max_steps

    def end_reason(self) -> str | None:
        """Why the episode ends at this step (one of END_REASONS), or None while it goes on."""
        if self.collision:
            return "collision"
        if self.offroad:
            return "offroad"
        if self.stalled:
            return "stalled"
        return "cap" if self.steps >= self.env_config.max_steps else None

    def _info(self) -> dict:
        return {"distance": self.distance, "collision": self.collision, "offroad": self.offroad,
                "stalled": self.stalled, "end": self.end_reason(),
                "progress_m": self.progress.total_m, "street": self.place_name, "pose": self.pose,
                "hit": self.hit,
                "streets_visited": tuple(sorted(self.streets_visited)),
                "lane_index": self.vehicle.lane_index, "start_set": self.start_set,
                "start_index": self.start_index, "step": self.steps}

    def render(self) -> np.ndarray | None:
        """With ``render_mode="rgb_array"``: the observation's camera at four times the resolution."""
        if self.render_mode != "rgb_array":
            return None
        camera = getattr(self.observation_type, "camera", self.env_config.camera)
        return self.cameras(camera).view(*self.pose, 4 * FRAME_SHAPE[1], 4 * FRAME_SHAPE[0],
                                         self.traffic_rectangles())


def _wrap_angle(angle: float) -> float:
    return math.remainder(angle, math.tau)
