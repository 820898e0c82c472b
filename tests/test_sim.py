"""The driving simulator (actor/sim): geometry, dynamics, camera, rewards, episodes, feasibility."""

from __future__ import annotations

import math
import warnings

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from actor.sim import ENV_ID, START_SETS, make_env, start_poses
from actor.sim.camera import FRAME_SHAPE
from actor.sim.env import NeighbourhoodEnv
from actor.sim.geometry import Obstacles, Segments
from actor.sim.kinematics import bicycle_step, turning_radius
from actor.sim.neighbourhood import neighbourhood
from actor.sim.privileged import PrivilegedDriver
from actor.sim.world_image import ASPHALT, CENTRE_DASH, GRASS, PARKED_CAR, TREE, world_image
from common.config import ConfigError, EnvConfig

STRAIGHT = 2  # action index of zero steering
# The hand-computed steps below assume 2 m per step: 10 m/s at 5 decisions per second.
CONFIG = EnvConfig(policy_frequency=5, start_jitter_m=0.0, start_jitter_deg=0.0)


@pytest.fixture(scope="module")
def env() -> NeighbourhoodEnv:
    return NeighbourhoodEnv(CONFIG)


def colour_count(frame: np.ndarray, colour) -> int:
    return int((frame == colour).all(axis=-1).sum())


# --- pure geometry and dynamics, against hand-computed values -------------------------------

def test_segment_distance_hand_values():
    segments = Segments(np.array([[0.0, 0.0], [10.0, 0.0]]), np.array([[10.0, 0.0], [10.0, 10.0]]))
    assert segments.distance(5.0, 3.0) == pytest.approx(3.0)  # beside the first
    assert segments.distance(13.0, 4.0) == pytest.approx(3.0)  # beside the second
    assert segments.distance(-3.0, -4.0) == pytest.approx(5.0)  # beyond an end
    assert segments.distance(10.0, 0.0) == 0.0


def test_collision_is_exact_for_rotated_rectangles_and_circles():
    # A 2 x 2 square turned 45 degrees, its corner sqrt(2) from its centre, ahead of a 4.5 x 1.8 car at the origin.
    half_diagonal = math.sqrt(2.0)
    def square_at(x):
        return Obstacles(rectangles=np.array([[x, 0.0, math.pi / 4, 2.0, 2.0]]), circles=np.zeros((0, 3)))
    assert square_at(2.25 + half_diagonal - 0.05).hits(0.0, 0.0, 0.0, 4.5, 1.8)
    assert not square_at(2.25 + half_diagonal + 0.05).hits(0.0, 0.0, 0.0, 4.5, 1.8)
    # A circle of radius 0.8 off the car's corner: 0.6 m out along both axes is 0.85 m away.
    near_corner = Obstacles(rectangles=np.zeros((0, 5)), circles=np.array([[2.25 + 0.6, 0.9 + 0.6, 0.8]]))
    assert not near_corner.hits(0.0, 0.0, 0.0, 4.5, 1.8)
    beside = Obstacles(rectangles=np.zeros((0, 5)), circles=np.array([[0.0, 0.9 + 0.99, 1.0]]))
    assert beside.hits(0.0, 0.0, 0.0, 4.5, 1.8)
    assert not beside.hits(0.0, -0.05, 0.0, 4.5, 1.8)


def test_bicycle_step_hand_values():
    # Straight: 10 m/s for 0.2 s.
    assert bicycle_step(1.0, 2.0, 0.0, 10.0, 0.0, 2.7, 0.2) == pytest.approx((3.0, 2.0, 0.0))
    # 25 degrees: beta = atan(0.466308 / 2) = 0.229062, sin(beta) = 0.227064,
    # yaw rate = 10 * 0.227064 / 1.35 = 1.681954 rad/s, so 0.336391 rad in 0.2 s.
    x, y, heading = bicycle_step(0.0, 0.0, 0.0, 10.0, math.radians(25), 2.7, 0.2)
    assert heading == pytest.approx(0.336391, abs=1e-5)
    # The centre stays on a circle of radius 1.35 / 0.227064 = 5.945465 m, centred to the right of its course.
    radius = turning_radius(math.radians(25), 2.7)
    assert radius == pytest.approx(5.945465, abs=1e-5)
    beta = 0.229062
    centre = (-radius * math.sin(beta), radius * math.cos(beta))
    assert math.hypot(x - centre[0], y - centre[1]) == pytest.approx(radius, abs=1e-6)
    assert y > 0  # positive steering turns right: towards +y in the y-down frame


# --- the map --------------------------------------------------------------------------------

def test_neighbourhood_is_a_connected_grid_with_corners_and_junctions():
    hood = neighbourhood()
    degrees = {name: len(near) for name, near in hood.neighbours.items()}
    assert min(degrees.values()) >= 2  # no dead end
    assert {2, 3, 4} <= set(degrees.values())  # corners, T- and X-junctions
    seen, frontier = set(), ["A1"]
    while frontier:
        junction = frontier.pop()
        if junction not in seen:
            seen.add(junction)
            frontier.extend(hood.neighbours[junction])
    assert seen == set(hood.junctions)
    x_min, y_min, x_max, y_max = hood.bounds(0.0)
    assert x_max - x_min >= 140 and y_max - y_min >= 140  # at least 2 x 2 blocks of ~70 m


def test_parked_cars_are_car_sized_and_some_block_the_centre_line():
    hood = neighbourhood()
    rectangles = np.array([car.rectangle for car in hood.parked_cars])
    assert np.allclose(rectangles[:, 3:], [4.5, 1.8])
    car_half_width = 0.9
    blocking = [car for car in hood.parked_cars if abs(car.offset) - car_half_width < car_half_width]
    assert len(blocking) >= 5  # a car on the centre-line would touch these
    assert all(abs(car.offset) - car_half_width < 3.7 for car in hood.parked_cars)  # on the road


def test_road_surface_drawn_is_where_the_car_is_on_the_road():
    world = world_image(CONFIG.render_scale, CONFIG.offroad_distance)
    hood = neighbourhood()
    rng = np.random.default_rng(0)
    rows = rng.integers(world.pixels.shape[0], size=4000)
    columns = rng.integers(world.pixels.shape[1], size=4000)
    road_colours = {ASPHALT, CENTRE_DASH, PARKED_CAR}
    for row, column in zip(rows, columns):
        x = world.x_min + (column + 0.5) / world.scale
        y = world.y_min + (row + 0.5) / world.scale
        colour = tuple(int(c) for c in world.rgb[row, column])
        distance = hood.centre_lines.distance(x, y)
        if distance < CONFIG.offroad_distance - 0.2:
            assert colour in road_colours, (x, y, distance, colour)
        elif distance > CONFIG.offroad_distance + 0.2:
            assert colour not in {ASPHALT, CENTRE_DASH}, (x, y, distance, colour)


# --- observation ----------------------------------------------------------------------------

def test_observation_shape_dtype_and_colours(env):
    observation, _ = env.reset(options={"start_index": 0})
    assert observation.shape == FRAME_SHAPE == (66, 200, 3)
    assert observation.dtype == np.uint8
    assert env.observation_space.contains(observation)
    for colour in (ASPHALT, GRASS, TREE, CENTRE_DASH):
        assert colour_count(observation, colour) > 0, colour


def test_parked_car_ahead_appears_where_the_camera_model_puts_it(env):
    env.reset(options={"start_index": 0})
    # Parked car on street A1-B1 at s = 22 m, 2.6 m right of the centre-line (layout.py): heading east
    # from x = 10, it is 12 m ahead and 2.6 m right. Column (2.6 + 12) / 0.12 - 0.5 = 121.2,
    # row (30 - 12) / (32 / 66) - 0.5 = 36.6.
    frame = env.place(10.0, 0.0, 0.0)
    assert tuple(frame[37, 121]) == PARKED_CAR
    cars = np.argwhere((frame == PARKED_CAR).all(axis=-1))
    assert cars[:, 1].min() > 100  # right half: the car is parked on the right
    # Turned round, the same two parked cars are behind it: out of view.
    assert colour_count(env.place(10.0, 0.0, math.pi), PARKED_CAR) == 0


def test_observation_is_a_fresh_array_each_step(env):
    first, _ = env.reset(options={"start_index": 0})
    second, *_ = env.step(STRAIGHT)
    assert not np.shares_memory(first, second)
    assert not np.array_equal(first, second)


# --- reward and episode ends ----------------------------------------------------------------

@pytest.mark.parametrize("offset", [0.0, 0.5, 1.0, 2.0])
def test_reward_is_one_on_the_centre_line_and_falls_with_distance(env, offset):
    env.reset(options={"start_index": 0})  # street A1-B1, heading east from x = 15
    env.place(15.0, -offset, 0.0)  # to the left, where nothing is parked
    _, reward, terminated, _, info = env.step(STRAIGHT)
    assert not terminated
    assert info["distance"] == pytest.approx(offset, abs=1e-9)
    assert reward == pytest.approx(math.exp(-0.8 * offset), abs=1e-9)


def test_collision_terminates_with_zero_reward_at_the_hand_computed_step(env):
    # From train start 0 (x = 15 on A1-B1, heading east) straight on: the car parked 1.3 m left at
    # s = 52 m reaches 0.4 m into the car's lane; the fronts meet when 15 + 2 k + 2.25 >= 52 - 2.25,
    # first at step k = 17.
    env.reset(options={"start_set": "train", "start_index": 0})
    for step in range(1, 18):
        _, reward, terminated, truncated, info = env.step(STRAIGHT)
        assert terminated == (step == 17)
    assert info["collision"] and not info["offroad"] and not truncated
    assert reward == 0.0
    assert info["step"] == 17


def test_leaving_the_road_terminates(env):
    env.reset(options={"start_index": 0})
    env.place(45.0, 0.0, -math.pi / 2)  # on A1-B1, facing north, straight off the road
    _, _, terminated, _, info = env.step(STRAIGHT)  # 2 m from the centre-line
    assert not terminated and info["distance"] == pytest.approx(2.0)
    _, reward, terminated, truncated, info = env.step(STRAIGHT)  # 4 m > 3.7 m
    assert terminated and info["offroad"] and not info["collision"] and not truncated
    assert reward == pytest.approx(math.exp(-0.8 * 4.0))


def test_truncation_at_the_step_cap():
    config = EnvConfig(max_steps=30)
    env = NeighbourhoodEnv(config)
    env.reset(options={"start_index": 0})
    driver = PrivilegedDriver(config)
    driver.reset(env.pose)
    for step in range(1, 31):
        _, _, terminated, truncated, info = env.step(driver.act(env.pose))
        assert not terminated
        assert truncated == (step == 30)
    assert info["step"] == 30


# --- start poses, options, bad input ---------------------------------------------------------

def test_start_sets_have_ten_disjoint_poses_on_the_road(env):
    train, test = start_poses("train"), start_poses("test")
    assert len(train) == len(test) == 10
    gaps = [math.hypot(a.x - b.x, a.y - b.y) for a in train for b in test]
    assert min(gaps) > 10.0
    for start_set in START_SETS:
        for index, pose in enumerate(start_poses(start_set)):
            _, info = env.reset(options={"start_set": start_set, "start_index": index})
            assert env.pose == (pose.x, pose.y, pose.heading)
            assert info["distance"] < 1e-9 and not info["collision"]
            assert (info["start_set"], info["start_index"], info["step"]) == (start_set, index, 0)


def test_start_is_drawn_from_the_set_with_the_env_rng(env):
    drawn = {env.reset(seed=seed)[1]["start_index"] for seed in range(40)}
    assert len(drawn) > 5
    assert env.reset(seed=3)[1] == env.reset(seed=3)[1]
    assert env.reset(options={"start_set": "test"})[1]["start_set"] == "test"
    assert env.reset()[1]["start_set"] == "train"


@pytest.mark.parametrize("options", [{"start_set": "validation"}, {"start_index": 10},
                                     {"start_index": -1}, {"start_index": 1.0}, {"start": 1}])
def test_bad_reset_options_are_config_errors(env, options):
    with pytest.raises(ConfigError):
        env.reset(options=options)


@pytest.mark.parametrize("action", [5, -1, 1.5, "left", True])
def test_bad_actions_are_config_errors(env, action):
    env.reset(options={"start_index": 0})
    with pytest.raises(ConfigError):
        env.step(action)


# --- determinism, gymnasium -----------------------------------------------------------------------

def test_same_seed_and_actions_give_the_same_episode():
    def run(seed):
        env = make_env(CONFIG, seed=seed)
        rng = np.random.default_rng(7)
        observations, rewards = [], []
        env.reset()
        for _ in range(150):
            observation, reward, terminated, truncated, info = env.step(int(rng.integers(5)))
            observations.append(observation)
            rewards.append((reward, info["start_index"]))
            if terminated or truncated:
                env.reset()
        return np.stack(observations), rewards
    first, second, other = run(11), run(11), run(12)
    assert np.array_equal(first[0], second[0]) and first[1] == second[1]
    assert first[1] != other[1]  # the seed does matter: other start draws


def test_registered_with_gymnasium_and_passes_the_env_checker():
    env = gymnasium.make(ENV_ID, env_config=CONFIG, render_mode="rgb_array")
    assert isinstance(env.unwrapped, NeighbourhoodEnv)
    assert env.action_space == gymnasium.spaces.Discrete(5)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a checker warning fails the test too
        check_env(env.unwrapped)
    env.reset(options={"start_index": 0})
    assert env.render().shape == (256, 192, 3)


def test_highway_env_grayscale_renderer_works_on_the_same_road():
    env = NeighbourhoodEnv(CONFIG, observation={"type": "GrayscaleObservation", "observation_shape": (200, 66),
                                                "stack_size": 1, "weights": [0.2989, 0.5870, 0.1140]})
    observation, _ = env.reset(options={"start_index": 0})
    observation, *_ = env.step(STRAIGHT)
    assert observation.shape == (1, 200, 66)
    assert observation.std() > 10  # lanes and obstacles drawn, not a blank frame
    assert len(env.road.network.lanes_list()) == len(neighbourhood().streets) + len(neighbourhood().turns)


# --- feasibility -------------------------------------------------------------------------------

def test_driving_straight_ends_in_a_crash_or_off_the_road_from_every_training_start(env):
    for index in range(10):
        env.reset(options={"start_set": "train", "start_index": index})
        for _ in range(CONFIG.max_steps):
            _, _, terminated, truncated, info = env.step(STRAIGHT)
            if terminated or truncated:
                break
        assert terminated and (info["collision"] or info["offroad"]), index


@pytest.mark.parametrize("config", [EnvConfig(), CONFIG], ids=["default", "5Hz"])
def test_privileged_driver_drives_full_episodes_from_the_training_starts(config):
    # 10 x 2,000 steps: a few seconds at the env's speed (see deploy/bench/env_speed.py).
    env = NeighbourhoodEnv(config)
    completed = 0
    for index in range(10):
        env.reset(options={"start_set": "train", "start_index": index})
        driver = PrivilegedDriver(config, seed=index)
        driver.reset(env.pose)
        terminated = truncated = False
        while not (terminated or truncated):
            _, _, terminated, truncated, info = env.step(driver.act(env.pose))
        completed += truncated and info["step"] == config.max_steps and not info["collision"]
    assert completed >= 8


def test_start_jitter_varies_the_start_within_its_bounds():
    config = EnvConfig(start_jitter_m=0.3, start_jitter_deg=3.0)
    env = NeighbourhoodEnv(config)
    pose = start_poses("train")[4]
    seen = set()
    for seed in range(20):
        _, info = env.reset(seed=seed, options={"start_index": 4})
        x, y, heading = env.pose
        sideways = (x - pose.x) * -math.sin(pose.heading) + (y - pose.y) * math.cos(pose.heading)
        along = (x - pose.x) * math.cos(pose.heading) + (y - pose.y) * math.sin(pose.heading)
        turn = math.degrees(math.remainder(heading - pose.heading, math.tau))
        assert abs(sideways) <= 0.3 + 1e-9 and abs(along) < 1e-9 and abs(turn) <= 3.0 + 1e-9
        assert info["distance"] == pytest.approx(abs(sideways), abs=1e-6)
        seen.add(round(sideways, 6))
    assert len(seen) == 20
    env.reset(seed=3, options={"start_index": 4})
    again = env.pose
    env.reset(seed=3, options={"start_index": 4})
    assert env.pose == again
