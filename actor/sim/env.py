"""The driving simulator: a highway-env ``AbstractEnv`` of a small urban neighbourhood.

The car holds a constant speed and only steers (five discrete angles); it sees
through a front camera; its reward is exp(-beta * d) with d its distance to
the nearest street centre-line, 0 on a collision. An episode ends on a
collision with a parked car, tree or house, or on leaving the road
(d > ``offroad_distance``); it is cut at ``max_steps``.

Why the step is our own: ``AbstractEnv.step`` runs highway-env's simulation
loop, where every ``Vehicle.step`` searches all lanes for the closest one and
``Road.step`` tests the car against every object with polygon code, in
Python, at every simulation frame. That costs far more than the whole step
budget (>= 1,000 steps/s with the camera). This class still is an
``AbstractEnv`` (its config, ``ObservationType``/``ActionType`` plumbing, a real
highway-env ``Road`` with a ``RoadNetwork`` and ``Obstacle`` objects, and a
highway-env ``Vehicle`` for the ego car, so highway-env's own renderers and
observations work on it), but ``step`` advances the ego car itself: the
kinematic bicycle of ``kinematics.py``, integrated exactly in one go, then
one vectorised distance and one vectorised collision query against arrays
precomputed from the same geometry (``neighbourhood.py``). ``reset`` is ours
too, so that the action and observation spaces are built once and keep their
seeds across episodes.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from highway_env import utils
from highway_env.envs.common.abstract import AbstractEnv
from highway_env.envs.common.action import ActionType
from highway_env.envs.common.observation import ObservationType, observation_factory
from highway_env.vehicle.kinematics import Vehicle

from actor.sim import layout
from actor.sim.camera import FRAME_SHAPE, FrontCamera
from actor.sim.kinematics import bicycle_step
from actor.sim.neighbourhood import Pose, neighbourhood
from actor.sim.road import neighbourhood_road
from actor.sim.world_image import world_image
from common.config import ConfigError, EnvConfig

STEERING_LEVELS = (-1.0, -0.5, 0.0, 0.5, 1.0)  # times the maximum angle; positive turns right
START_SETS = ("train", "test")
OPTION_KEYS = ("start_set", "start_index")


class SteeringAction(ActionType):
    """``Discrete(5)``: steering angle = level x maximum angle; the speed never changes."""

    def __init__(self, env: AbstractEnv, max_steering: float, **kwargs: Any) -> None:
        super().__init__(env)
        self.max_steering = max_steering

    def space(self) -> spaces.Discrete:
        return spaces.Discrete(len(STEERING_LEVELS))

    @property
    def vehicle_class(self) -> type:
        return Vehicle

    def steering(self, action: Any) -> float:
        """The steering angle in radians of an action index; a clear error for anything else."""
        if isinstance(action, np.ndarray) and action.shape == ():
            action = action.item()
        if isinstance(action, (bool, np.bool_)) or not isinstance(action, (int, np.integer)) \
                or not 0 <= action < len(STEERING_LEVELS):
            raise ConfigError(f"action: must be an integer in [0, {len(STEERING_LEVELS)}), got {action!r}")
        return STEERING_LEVELS[int(action)] * self.max_steering

    def act(self, action: Any) -> None:
        self.controlled_vehicle.action = {"steering": self.steering(action), "acceleration": 0.0}


class FrontCameraObservation(ObservationType):
    """The heading-up colour frame of ``camera.py``: uint8 RGB, shape (66, 200, 3)."""

    def space(self) -> spaces.Box:
        return spaces.Box(low=0, high=255, shape=FRAME_SHAPE, dtype=np.uint8)

    def observe(self) -> np.ndarray:
        return self.env.camera.frame(*self.env.pose)


class NeighbourhoodEnv(AbstractEnv):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 5}

    def __init__(self, env_config: EnvConfig | None = None, render_mode: str | None = None,
                 observation: dict | None = None) -> None:
        """``observation`` swaps the camera for a highway-env observation config (benchmarks)."""
        self.env_config = env_config if env_config is not None else EnvConfig()
        self.env_config.validate()
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ConfigError(f"render_mode: must be one of {self.metadata['render_modes']} or None")
        self.hood = neighbourhood()
        scale, half_width = self.env_config.render_scale, self.env_config.offroad_distance
        self.camera = FrontCamera(world_image(scale, half_width), self.env_config.camera_ahead_m,
                                  self.env_config.camera_behind_m, self.env_config.camera_width_m)
        self.pose = (0.0, 0.0, 0.0)
        self.start_set, self.start_index = START_SETS[0], 0
        self.distance, self.collision = 0.0, False
        self.metadata = {**self.metadata, "render_fps": self.env_config.policy_frequency}
        frequency = self.env_config.policy_frequency
        super().__init__({"observation": observation or {"type": "FrontCamera"},
                          "policy_frequency": frequency, "simulation_frequency": frequency},
                         render_mode)

    @classmethod
    def default_config(cls) -> dict:
        config = super().default_config()
        utils.update_config(config, {"observation": {"type": "FrontCamera"},
                                     "action": {"type": "SteeringAction"}})
        return config

    def define_spaces(self) -> None:
        observation = self.config["observation"]
        if observation["type"] == "FrontCamera":
            self.observation_type = FrontCameraObservation(self)
        else:
            self.observation_type = observation_factory(self, observation)
        self.action_type = SteeringAction(self, math.radians(self.env_config.max_steer_deg))
        self.observation_space = self.observation_type.space()
        self.action_space = self.action_type.space()

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
        return observation, self._info(observation)

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
            self.road = neighbourhood_road(self.hood, self.env_config.offroad_distance)
            self.vehicle = self._ego_vehicle()
            self.road.vehicles.append(self.vehicle)
        start: Pose = self.hood.start_poses[self.start_set][self.start_index]
        self.vehicle.crashed = False
        self._move_to(*self._jittered(start))

    def _jittered(self, start: Pose) -> tuple[float, float, float]:
        """The start pose moved sideways and turned by uniform draws within the configured bounds."""
        if self.env_config.start_jitter_m == 0 and self.env_config.start_jitter_deg == 0:
            return start.x, start.y, start.heading
        shift = self.np_random.uniform(-1.0, 1.0) * self.env_config.start_jitter_m
        turn = math.radians(self.np_random.uniform(-1.0, 1.0) * self.env_config.start_jitter_deg)
        sideways_x, sideways_y = -math.sin(start.heading), math.cos(start.heading)
        return start.x + shift * sideways_x, start.y + shift * sideways_y, _wrap_angle(start.heading + turn)

    def _ego_vehicle(self) -> Vehicle:
        vehicle = self.action_type.vehicle_class(self.road, [0.0, 0.0], 0.0, self.env_config.speed)
        vehicle.LENGTH, vehicle.WIDTH = layout.CAR_LENGTH_M, layout.CAR_WIDTH_M
        vehicle.diagonal = math.hypot(vehicle.LENGTH, vehicle.WIDTH)
        return vehicle

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict]:
        if self.road is None:
            raise ConfigError("step: call reset() first")
        self.action_type.act(action)
        x, y, heading = bicycle_step(*self.pose, self.env_config.speed,
                                     self.vehicle.action["steering"], self.env_config.wheelbase_m,
                                     1.0 / self.env_config.policy_frequency)
        self._move_to(x, y, _wrap_angle(heading))
        self.steps += 1
        self.time += 1.0 / self.env_config.policy_frequency
        observation = self.observation_type.observe()
        return (observation, self._reward(action), self._is_terminated(), self._is_truncated(),
                self._info(observation, action))

    def place(self, x: float, y: float, heading: float) -> np.ndarray:
        """Puts the car at a pose in the current episode (tests, pictures); returns the observation."""
        if self.road is None:
            raise ConfigError("place: call reset() first")
        self._move_to(float(x), float(y), _wrap_angle(float(heading)))
        return self.observation_type.observe()

    def _move_to(self, x: float, y: float, heading: float) -> None:
        """Places the ego car and measures where it now is: distance to the road, collision."""
        self.pose = (x, y, heading)
        self.vehicle.position[:] = (x, y)
        self.vehicle.heading = heading
        self.distance = self.hood.centre_lines.distance(x, y)
        self.collision = self.hood.obstacles.hits(x, y, heading, layout.CAR_LENGTH_M, layout.CAR_WIDTH_M)
        self.vehicle.crashed = self.vehicle.crashed or self.collision

    # --- reward, ends, info --------------------------------------------------------------------

    @property
    def offroad(self) -> bool:
        return self.distance > self.env_config.offroad_distance

    def _reward(self, action: Any) -> float:
        return 0.0 if self.collision else math.exp(-self.env_config.reward_beta * self.distance)

    def _is_terminated(self) -> bool:
        return self.collision or self.offroad

    def _is_truncated(self) -> bool:
        return not self._is_terminated() and self.steps >= self.env_config.max_steps

    def _info(self, obs: Any, action: Any = None) -> dict:
        return {"distance": self.distance, "collision": self.collision, "offroad": self.offroad,
                "start_set": self.start_set, "start_index": self.start_index, "step": self.steps}

    def render(self) -> np.ndarray | None:
        """With ``render_mode="rgb_array"``: the camera window at full world resolution."""
        if self.render_mode != "rgb_array":
            return None
        config, scale = self.env_config, self.env_config.render_scale
        columns = int(round(config.camera_width_m * scale))
        rows = int(round((config.camera_ahead_m + config.camera_behind_m) * scale))
        return self.camera.view(*self.pose, columns, rows)


def _wrap_angle(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi
