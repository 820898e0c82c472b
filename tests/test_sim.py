"""The driving simulator (actor/sim): geometry, dynamics, camera, rewards, episodes, feasibility."""

from __future__ import annotations

import math
import warnings

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from actor.sim import ENV_ID, START_SETS, make_env, start_poses
from highway_env.vehicle.kinematics import Vehicle

from actor.sim.camera import FRAME_SHAPE
from actor.sim.collision_site import parked_car_name, touched
from actor.sim.env import NeighbourhoodEnv
from actor.sim.geometry import Obstacles, Segments
from actor.sim.neighbourhood import crossed_junction, is_street, neighbourhood, place_counts, places_reached
from actor.sim.privileged import PrivilegedDriver
from actor.sim.progress import ProgressMeter
from actor.sim.road import LaneLocator, road_network
from actor.sim.world_image import ASPHALT, CENTRE_DASH, GRASS, PARKED_CAR, TREE, world_image
from common.sim_config import EnvConfig
from common.schema.fields import ConfigError

STRAIGHT = 2  # action index of zero steering
# The hand-computed steps below assume 2 m per step: 10 m/s at 5 decisions per second. The
# pixel tests read the top-down camera's map geometry (the front camera has tests of its own).
CONFIG = EnvConfig(policy_frequency=5, start_jitter_m=0.0, start_jitter_deg=0.0, camera="topdown")
TOPDOWN = EnvConfig(camera="topdown")  # the default dynamics, a cheap camera


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


def test_the_ego_car_moves_by_highway_envs_own_vehicle_step(env):
    env.reset(options={"start_index": 0})
    env.place(15.0, 0.0, 0.0)
    reference = Vehicle(None, [15.0, 0.0], 0.0, CONFIG.speed)
    reference.LENGTH = 4.5
    reference.act({"steering": math.radians(25), "acceleration": 0.0})
    for _ in range(CONFIG.simulation_frequency // CONFIG.policy_frequency):
        reference.step(1.0 / CONFIG.simulation_frequency)
    env.step(4)  # full right
    assert env.pose == pytest.approx((*reference.position, reference.heading), abs=1e-12)
    assert env.vehicle.speed == CONFIG.speed


def test_full_steering_turns_on_highway_envs_radius():
    # beta = atan(tan(25 deg) / 2) = 0.229062 rad, sin(beta) = 0.227064: heading rate
    # 10 * 0.227064 / 2.25 = 1.009173 rad/s, so the centre circles at 10 / 1.009173 = 9.909 m.
    env = NeighbourhoodEnv(EnvConfig(camera="topdown", offroad_distance=11.0, start_jitter_m=0.0,
                                     start_jitter_deg=0.0, simulation_frequency=200))
    env.reset(options={"start_index": 0})
    x0, y0 = env.hood.junctions["B2"]
    env.place(x0, y0 - 9.909, 0.0)
    # The centre's velocity points beta right of the heading; the circle's centre lies square to it.
    centre = (x0 - 9.909 * math.sin(0.229062), y0 - 9.909 + 9.909 * math.cos(0.229062))
    points = []
    for _ in range(30):
        env.step(4)
        points.append(env.pose[:2])
    radii = np.hypot(*(np.array(points) - centre).T)
    assert radii == pytest.approx(9.909, abs=0.05)  # Euler at 200 Hz: centimetres off the circle
    assert env.pose[2] == pytest.approx(math.remainder(30 * 0.1 * 1.009173, math.tau), abs=1e-3)


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
    assert info["hit"] == "parked car on A1-B1 52 m from A1, 1.3 m left of the centre-line"
    # the pose of the frame in which the fronts met: 52 - 2.25 - 2.25
    assert info["street"] == "A1-B1" and info["pose"] == pytest.approx((47.5, 0.0, 0.0), abs=1e-6)


def test_a_collision_names_what_it_touched():
    hood = neighbourhood()
    car = hood.parked_cars[4]  # B1-C1, 45 m from B1 (x = 120), 0.9 m right (y = 0.9): its edge on the centre-line
    assert touched(hood, (120.0, -0.5, math.pi)) == parked_car_name(car)  # passing it 0.5 m off the centre-line
    assert touched(hood, (120.0, -1.0, math.pi)) == ""  # 1 m off: 0.1 m to spare
    tree_x, tree_y, radius = hood.trees[0]
    assert touched(hood, (tree_x + radius + 1.0, tree_y, 0.0)) == "a tree"
    house = hood.houses[0]
    assert touched(hood, (house[0], house[1], 0.0)) == "a house"
    traffic = np.array([[60.0, 0.0, 0.0, 4.5, 1.8]])  # on A1-B1, 8 m past its last parked car
    assert touched(hood, (62.0, 0.0, 0.0), traffic) == "a traffic car" and touched(hood, (62.0, 0.0, 0.0)) == ""


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
    assert env.render().shape == (4 * 66, 4 * 200, 3)


def test_highway_env_grayscale_renderer_works_on_the_same_road():
    env = NeighbourhoodEnv(CONFIG, observation={"type": "GrayscaleObservation", "observation_shape": (200, 66),
                                                "stack_size": 1, "weights": [0.2989, 0.5870, 0.1140]})
    observation, _ = env.reset(options={"start_index": 0})
    observation, *_ = env.step(STRAIGHT)
    assert observation.shape == (1, 200, 66)
    assert observation.std() > 10  # lanes and obstacles drawn, not a blank frame


@pytest.mark.parametrize("observation", [
    {"type": "Kinematics"},
    {"type": "OccupancyGrid", "features": ["presence", "vx", "vy"], "grid_size": [[-20, 20], [-20, 20]],
     "grid_step": [2, 2], "absolute": False},
    {"type": "TimeToCollision", "horizon": 5},
], ids=["Kinematics", "OccupancyGrid", "TimeToCollision"])
def test_highway_env_observation_types_run_on_the_env(observation):
    env = NeighbourhoodEnv(TOPDOWN, observation=observation)
    first, _ = env.reset(options={"start_index": 0})
    driver = PrivilegedDriver(TOPDOWN)
    driver.reset(env.pose)
    for _ in range(300):  # round corners and through junctions: the lane index keeps up
        later, *_ = env.step(driver.act(env.pose))
    if observation["type"] != "TimeToCollision":  # its space assumes three lanes side by side
        assert env.observation_space.contains(first) and env.observation_space.contains(later)
    assert np.all(np.isfinite(later))


def test_highway_env_action_config_is_honoured():
    env = NeighbourhoodEnv(TOPDOWN, action={"type": "ContinuousAction", "longitudinal": False, "lateral": True})
    assert isinstance(env.action_space, gymnasium.spaces.Box)
    env.reset(options={"start_index": 0})
    start = env.pose
    env.step(np.array([0.0], dtype=np.float32))
    moved = math.hypot(env.pose[0] - start[0], env.pose[1] - start[1])
    assert moved == pytest.approx(1.0, abs=1e-9) and env.pose[2] == start[2]  # 10 m/s for 0.1 s, straight


# --- the road network: highway-env's lanes -----------------------------------------------------

def test_road_network_is_a_connected_two_way_lane_graph():
    network = road_network(neighbourhood(), 2.0, 3.4)
    lanes = [(a, b, i) for a, tos in network.graph.items() for b, lanes in tos.items() for i in range(len(lanes))]
    hood = neighbourhood()
    assert len(lanes) == 2 * len(hood.streets) + sum(len(n) * (len(n) - 1) for n in hood.neighbours.values())
    for lane_index in lanes:
        lane = network.get_lane(lane_index)
        successors = network.graph.get(lane_index[1], {})
        assert successors, lane_index  # every lane leads somewhere
        for after in successors:
            following = network.get_lane((lane_index[1], after, 0))
            assert np.allclose(following.position(0, 0), lane.position(lane.length, 0), atol=1e-9)
            assert math.remainder(following.heading_at(0) - lane.heading_at(lane.length), math.tau) == \
                pytest.approx(0.0, abs=1e-9)
    nodes = list(network.graph)
    assert all(network.shortest_path(nodes[0], node) for node in nodes[1:])  # strongly connected...
    assert all(network.shortest_path(node, nodes[0]) for node in nodes[1:])
    # ...and both ways: each street has a lane each way, 2 m right of the centre-line.
    forth, back = network.get_lane(("A1>B1", "B1<A1", 0)), network.get_lane(("B1>A1", "A1<B1", 0))
    assert forth.position(10, 0)[1] == pytest.approx(2.0) and back.position(10, 0)[1] == pytest.approx(-2.0)


def test_the_ego_lane_index_is_a_closest_lane_of_its_direction_at_every_step():
    env = NeighbourhoodEnv(TOPDOWN)
    env.reset(options={"start_index": 3})
    driver = PrivilegedDriver(TOPDOWN, seed=1)
    driver.reset(env.pose)
    network = env.road.network
    lanes = network.lanes_dict()
    changes = 0
    for step in range(400):
        before = env.vehicle.lane_index
        env.step(driver.act(env.pose))
        changes += env.vehicle.lane_index != before
        if step % 7:  # highway-env's own search is slow: every 7th step
            continue
        position, heading = env.vehicle.position, env.vehicle.heading
        expected = network.get_closest_lane_index(position, heading)
        ours = network.get_lane(env.vehicle.lane_index)
        assert env.vehicle.lane is ours
        # Where lanes overlap (a junction's lanes share their start) any of the nearest will do.
        assert ours.distance_with_heading(position, heading) <= \
            lanes[expected].distance_with_heading(position, heading) + 0.35, step
        assert abs(math.remainder(ours.heading_at(ours.local_coordinates(position)[0]) - heading, math.tau)) < 1.0
    assert 8 <= changes <= 30  # about 400 m of streets and junctions, two lanes per block, no flicker


def test_lane_locator_gives_lane_coordinates():
    network = road_network(neighbourhood(), 2.0, 3.4)
    place = LaneLocator(network).locate(30.0, 2.5, 0.0)  # on A1-B1, heading east, 0.5 m right of its lane
    lane = network.get_lane(place.index)
    assert place.index == ("A1>B1", "B1<A1", 0)
    assert (place.longitudinal, place.lateral) == pytest.approx(lane.local_coordinates(np.array([30.0, 2.5])))
    assert LaneLocator(network).locate(30.0, -1.0, math.pi).index == ("B1>A1", "A1<B1", 0)


def test_simulators_of_a_process_share_the_road_lookups_and_place_obstacles_as_highway_env_does():
    first, second = NeighbourhoodEnv(TOPDOWN), NeighbourhoodEnv(TOPDOWN)
    assert first.vehicle.locator is second.vehicle.locator  # built once, read only
    assert first.road is not second.road and first.road.network is not second.road.network
    network = second.road.network
    for obstacle in second.road.objects[::25]:  # highway-env's own search is slow: a sample
        assert obstacle.road is second.road
        assert obstacle.lane_index == network.get_closest_lane_index(obstacle.position, obstacle.heading)
        assert obstacle.lane is network.get_lane(obstacle.lane_index)


# --- progress and the stall rule ---------------------------------------------------------------

def _meter(memory=20, window=10, minimum=5.0) -> ProgressMeter:
    # Two pieces of 100 m, end to end: cells of 1 m, 0-99 on the first and 100-199 on the second.
    lines = Segments(np.array([[0.0, 0.0], [100.0, 0.0]]), np.array([[100.0, 0.0], [200.0, 0.0]]))
    return ProgressMeter(lines, memory, window, minimum, step_m=10.0)


def test_progress_counts_new_road_once_within_its_memory():
    meter = _meter(memory=20)
    meter.reset(0, 0.0)
    assert meter.update(0, 0.035) == pytest.approx(3.0)  # cells 1, 2, 3 are new (0 was the start)
    assert meter.update(0, 0.035) == 0.0  # standing still
    assert meter.update(0, 0.005) == 0.0  # back over driven road: cells 0-3, seen now (step 3)
    assert meter.update(0, 0.065) == pytest.approx(3.0)  # cells 4, 5, 6; 0-6 seen at step 4
    for _ in range(20):
        assert meter.update(0, 0.065) == 0.0  # steps 5-24 at cell 6
    # Step 25, back over cells 5 to 0: last seen at step 4, more than 20 steps ago.
    assert meter.update(0, 0.005) == pytest.approx(6.0)
    assert meter.total_m == pytest.approx(12.0)


def test_progress_across_pieces_is_the_gap_between_nearest_points():
    meter = _meter(memory=20)
    meter.reset(0, 0.985)
    assert meter.update(1, 0.015) == pytest.approx(3.0)  # from x = 98.5 to x = 101.5
    assert meter.update(0, 0.985) == 0.0  # back: cell 98 was the start
    meter = ProgressMeter(meter.centre_lines, 20, 10, 5.0, step_m=2.0)
    meter.reset(0, 0.5)
    assert meter.update(1, 0.5) == pytest.approx(2.0)  # never more than a step's drive


def test_stalled_only_after_a_full_window_of_too_little_progress():
    meter = _meter(window=10, minimum=5.0)
    meter.reset(0, 0.0)
    for step in range(1, 10):
        meter.update(0, 0.0)
        assert not meter.stalled, step  # window not yet full
    meter.update(0, 0.0)
    assert meter.stalled
    meter = _meter(window=10, minimum=5.0)
    meter.reset(0, 0.0)
    for step in range(1, 40):
        meter.update(0, step * 0.006)  # 0.6 m per step: 6 m per window of 10
        assert not meter.stalled


def test_circling_on_a_junction_ends_off_the_road_now():
    # highway-env's bicycle turns on 9.9 m at full lock, wider than any junction's paving: holding
    # full steering anywhere around the X-junction B2 leaves the road within a few dozen steps.
    env = NeighbourhoodEnv(EnvConfig(camera="topdown", start_jitter_m=0.0, start_jitter_deg=0.0))
    x0, y0 = env.hood.junctions["B2"]
    for action in (0, 4):
        for dx, dy, heading in [(0, 0, 0), (-6, 2, 0.5), (3, -4, 2.0), (0, -6, math.pi)]:
            env.reset(options={"start_index": 0})
            env.place(x0 + dx, y0 + dy, heading)
            for step in range(1, 2001):
                *_, terminated, truncated, info = env.step(action)
                if terminated or truncated:
                    break
            assert terminated and info["end"] in ("offroad", "collision") and step < 100


def test_circling_where_the_road_allows_it_ends_as_stalled():
    # On a 22 m wide road a full-lock circle (9.9 m) fits round the X-junction: it never leaves
    # the road or hits anything, and ends as stalled instead of reaching the cap.
    env = NeighbourhoodEnv(EnvConfig(camera="topdown", offroad_distance=11.0, start_jitter_m=0.0,
                                     start_jitter_deg=0.0))
    x0, y0 = env.hood.junctions["B2"]
    env.reset(options={"start_index": 0})
    env.place(x0, y0 - 9.9, 0.0)
    for step in range(1, 2001):
        _, reward, terminated, truncated, info = env.step(4)
        if terminated or truncated:
            break
    assert terminated and not truncated and info["end"] == "stalled" and info["stalled"]
    assert not info["collision"] and not info["offroad"] and reward > 0
    assert step < 2 * 100 + 63  # the window of 100 steps after one lap of 63 steps at most
    assert info["progress_m"] < 0.75 * step  # against about a metre per step for real driving


def test_info_reports_progress_street_and_streets_visited():
    env = NeighbourhoodEnv(TOPDOWN)
    _, info = env.reset(options={"start_index": 0})  # on A1-B1, heading east
    assert (info["street"], info["streets_visited"], info["progress_m"], info["end"]) == \
        ("A1-B1", ("A1-B1",), 0.0, None)
    driver = PrivilegedDriver(TOPDOWN, seed=0)
    driver.reset(env.pose)
    for _ in range(200):
        _, _, terminated, truncated, info = env.step(driver.act(env.pose))
    assert not (terminated or truncated)
    assert 180 <= info["progress_m"] <= 200  # about a metre of new road per step of 1 m
    assert info["street"] in info["streets_visited"] and len(info["streets_visited"]) >= 3
    assert info["streets_visited"][0] == "A1-B1" or "A1-B1" in info["streets_visited"]


def test_place_names_count_as_streets_or_junctions():
    # the streets A1-B1, B2-C2 (twice) and C1-C2, the junctions B2, C2 and D3
    assert place_counts(("A1-B1", "B2", "B2-C2", "C2", "C1-C2", "D3", "B2-C2")) == (3, 3)
    assert place_counts(()) == (0, 0)
    hood = neighbourhood()
    assert all(is_street(name) for name in hood.centre_line_places[:len(hood.streets)])
    assert not any(is_street(name) for name in hood.junctions)
    # 16 streets; 11 of the 12 junctions have corner curves: C3 is a straight run (C2-C3 is left out)
    assert place_counts(hood.centre_line_places) == (16, 11)


def test_a_junction_is_crossed_between_two_streets_that_end_at_it():
    assert crossed_junction("B3-C3", "C3-D3") == "C3"  # straight over C3
    assert crossed_junction("A2-B2", "B1-B2") == "B2"  # a corner cut short of its curve
    assert crossed_junction("A2-B2", "B2") is None  # onto the corner curve: the junction is the place itself
    assert crossed_junction("A1-B1", "A1-B1") is None and crossed_junction("A1-B1", "C1-D1") is None


def test_a_street_is_reached_away_from_its_junctions():
    hood = neighbourhood()
    segment = hood.centre_line_places.index("A2-B2")  # 75 m from A2 (0, 70) to B2 (75, 70)
    assert places_reached(hood, segment, 30 / 75, 3.7) == ("A2-B2",)
    assert places_reached(hood, segment, 72 / 75, 3.7) == ()  # 3 m from B2: maybe only crossing it
    assert places_reached(hood, segment, 2 / 75, 3.7, before="A1-A2") == ("A2",)
    assert places_reached(hood, segment, 10 / 75, 3.7, before="A2-A3") == ("A2-B2", "A2")
    corner = hood.centre_line_places.index("D3")  # the first of the 12 chords of its curve, 18.8 m in all
    assert places_reached(hood, corner, 0.5, 3.7, before="D2-D3") == ()  # 0.8 m into the curve
    assert places_reached(hood, corner + 6, 0.0, 3.7, before="D3") == ("D3",)  # half way round


def test_crossing_a_junction_visits_it_and_not_the_cross_street():
    env = NeighbourhoodEnv(EnvConfig(camera="topdown", start_jitter_m=0.0, start_jitter_deg=0.0))
    env.reset(options={"start_set": "train", "start_index": 7})  # on C3-D3, 50 m east of C3, heading west
    for _ in range(60):  # straight on over C3 (no corner curve there), 10 m into B3-C3
        _, _, terminated, _, info = env.step(STRAIGHT)
        assert not terminated
    assert info["streets_visited"] == ("B3-C3", "C3", "C3-D3")
    env.reset(options={"start_set": "test", "start_index": 3})  # on A2-B2, 20 m west of B2, heading east
    x, y, heading = env.pose
    env.place(x, y - 2.0, heading)  # 2 m north of the line: nearest the end of B1-B2 for 2 m in the junction
    streets_on_the_way = set()
    for _ in range(40):  # straight over the X-junction B2, 20 m into B2-C2
        _, _, terminated, _, info = env.step(STRAIGHT)
        streets_on_the_way.add(info["street"])
        assert not terminated
    assert "B1-B2" in streets_on_the_way
    assert info["streets_visited"] == ("A2-B2", "B2", "B2-C2")


def test_the_right_turning_driver_loops_one_block():
    env = NeighbourhoodEnv(TOPDOWN)
    env.reset(seed=0, options={"start_set": "test", "start_index": 0})  # on B1-C1 heading east
    driver = PrivilegedDriver(TOPDOWN, turns="right")
    driver.reset(env.pose)
    for _ in range(600):  # twice round the block of 290 m: right at C1, C2, B2, B1, C1, ...
        _, _, terminated, _, info = env.step(driver.act(env.pose))
        assert not terminated
    assert info["streets_visited"] == ("B1", "B1-B2", "B1-C1", "B2", "B2-C2", "C1", "C1-C2", "C2")
    assert place_counts(info["streets_visited"]) == (4, 4)
    with pytest.raises(ValueError, match="turns"):
        PrivilegedDriver(TOPDOWN, turns="u-turn")


# --- feasibility -------------------------------------------------------------------------------

def test_driving_straight_ends_in_a_crash_or_off_the_road_from_every_start(env):
    for start_set in START_SETS:
        for index in range(10):
            env.reset(options={"start_set": start_set, "start_index": index})
            for _ in range(CONFIG.max_steps):
                _, _, terminated, truncated, info = env.step(STRAIGHT)
                if terminated or truncated:
                    break
            assert terminated and info["end"] in ("collision", "offroad"), (start_set, index)


def drive_privileged(config: EnvConfig, start_set: str, index: int) -> dict:
    env = NeighbourhoodEnv(config)
    env.reset(seed=index, options={"start_set": start_set, "start_index": index})
    driver = PrivilegedDriver(config, seed=index)
    driver.reset(env.pose)
    terminated = truncated = False
    while not (terminated or truncated):
        _, _, terminated, truncated, info = env.step(driver.act(env.pose))
    return info


@pytest.mark.parametrize("config, starts", [(TOPDOWN, range(10)), (CONFIG, (0, 4, 8))], ids=["10Hz", "5Hz"])
@pytest.mark.parametrize("start_set", START_SETS)
def test_privileged_driver_drives_full_episodes_from_every_start(config, starts, start_set):
    # The camera plays no part in the dynamics; the top-down one is the cheaper to render.
    # Every start at the default 10 Hz; a few at 5 Hz, where a step is 2 m of road.
    for index in starts:
        info = drive_privileged(config, start_set, index)
        assert info["end"] == "cap" and info["step"] == config.max_steps, (start_set, index, info["end"])
        assert info["progress_m"] > 0.9 * config.max_steps * config.speed / config.policy_frequency


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
