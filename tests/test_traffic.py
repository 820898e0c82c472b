"""Moving traffic (actor/sim/traffic.py): lanes and profiles, determinism, collisions, cameras,
highway-env observations, giving way, and the privileged driver's feasibility with traffic."""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest

from actor.sim import layout
from actor.sim.env import NeighbourhoodEnv
from actor.sim.geometry import rectangle_corners
from actor.sim.privileged import PrivilegedDriver
from actor.sim.traffic import TrafficVehicle, is_street
from actor.sim.world_image import TRAFFIC_CAR
from common.sim_config import EnvConfig

STRAIGHT = 2  # action index of zero steering
TOPDOWN = EnvConfig(camera="topdown", traffic_vehicles=3)
BUSY = EnvConfig(camera="topdown", traffic_vehicles=6)
ONE = EnvConfig(camera="topdown", traffic_vehicles=1)  # for tests that put the one car where they need it
FAR_AWAY = np.array([-500.0, -500.0])  # beyond every camera and highway-env's perception distance


def drive(env: NeighbourhoodEnv, driver: PrivilegedDriver, steps: int):
    """Steps the env with the traffic-aware privileged driver; yields after every step."""
    for _ in range(steps):
        _, _, terminated, truncated, info = env.step(driver.act(env.pose, env.traffic_rectangles()))
        yield info
        if terminated or truncated:
            return


def started(config: EnvConfig, seed: int, start_set: str = "train", index: int = 0):
    env = NeighbourhoodEnv(config)
    env.reset(seed=seed, options={"start_set": start_set, "start_index": index})
    driver = PrivilegedDriver(config, seed=seed)
    driver.reset(env.pose)
    return env, driver


def park(vehicle: TrafficVehicle, x: float, y: float, heading: float) -> None:
    """Holds a traffic car still at a pose (for the tests that need one where the ego car goes)."""
    vehicle.position = np.array([x, y], dtype=np.float64)
    vehicle.heading, vehicle.speed, vehicle.target_speed = heading, 0.0, 1e-3
    vehicle.free_speed, vehicle.free_distance = vehicle._free_road(1e-3)
    vehicle.slow_speed, vehicle.slow_distance = vehicle.free_speed, vehicle.free_distance


def ahead_of(env: NeighbourhoodEnv, metres: float, right: float = 0.0) -> tuple[float, float, float]:
    x, y, heading = env.pose
    return (x + metres * math.cos(heading) - right * math.sin(heading),
            y + metres * math.sin(heading) + right * math.cos(heading), heading)


# --- lanes and profiles ------------------------------------------------------------------------

def test_every_lane_profile_passes_the_parked_cars_on_the_road():
    env = NeighbourhoodEnv(TOPDOWN)
    hood = env.hood
    for index, shape in env.traffic.shapes.items():
        # The car's body points along its course: the lane heading turned by the profile's slope.
        headings = [shape.heading(u) + math.atan(shape.target(u)[1]) for u in shape.path_u]
        for (x, y), heading in zip(shape.path_xy, headings):
            assert not hood.obstacles.hits(x, y, heading, layout.CAR_LENGTH_M, layout.CAR_WIDTH_M), index
            assert hood.centre_lines.distance(x, y) + layout.CAR_WIDTH_M / 2 <= TOPDOWN.offroad_distance + 1e-6
        if is_street(index):
            assert shape.offset.max() <= 0.0  # aside towards the centre-line only, never onto the kerb


def test_traffic_moves_along_its_lanes_on_the_road_and_never_into_a_parked_car():
    """Six cars with the privileged driver for 40 s: every body on the road surface, none in a
    parked car, tree or house, each car on its profile."""
    env, driver = started(BUSY, seed=3)
    vehicles = env.traffic.vehicles
    start = env.traffic.rectangles()[:, :2].copy()
    travelled = np.zeros(len(vehicles))
    previous = start.copy()
    for _ in drive(env, driver, 400):
        now = env.traffic.rectangles()
        travelled += np.hypot(*(now[:, :2] - previous).T)
        previous = now[:, :2].copy()
        for vehicle, (x, y, heading, length, width), corners in zip(vehicles, now, rectangle_corners(now)):
            assert not env.hood.obstacles.hits(x, y, heading, length, width)
            assert max(env.hood.centre_lines.distance(*corner) for corner in corners) <= BUSY.offroad_distance
            shape = env.traffic.shapes[vehicle.target_lane_index]
            u, lateral = shape.local(vehicle.position)
            assert abs(lateral - shape.target(u)[0]) < 0.35  # on its lane's profile
    assert env.steps == 400  # the privileged driver survived them
    # Everyone drove, each on its own route and at its own speed (giving way, some wait a while).
    assert np.all(travelled > 15.0) and travelled.mean() > 80.0
    speeds = {round(vehicle.target_speed, 3) for vehicle in vehicles}
    assert len(speeds) == len(vehicles)
    assert all(BUSY.traffic_speed_min <= speed <= BUSY.traffic_speed_max for speed in speeds)


def test_traffic_is_in_road_vehicles_with_a_current_lane_index():
    env, driver = started(TOPDOWN, seed=1)
    for _ in drive(env, driver, 200):
        pass
    for vehicle in env.traffic.vehicles:
        assert vehicle in env.road.vehicles
        assert isinstance(vehicle, TrafficVehicle) and not vehicle.enable_lane_change
        lane = env.road.network.get_lane(vehicle.lane_index)
        assert lane.distance(vehicle.position) < 4.0  # its lane, or just past its end


# --- determinism -------------------------------------------------------------------------------

def trajectory(seed: int, steps: int = 80) -> np.ndarray:
    env, driver = started(TOPDOWN, seed=seed)
    rows = [env.traffic.rectangles()]
    for _ in drive(env, driver, steps):
        rows.append(env.traffic.rectangles())
    return np.array(rows)


def test_same_seed_same_traffic_other_seed_other_traffic():
    first, again, other = trajectory(7), trajectory(7), trajectory(8)
    assert np.array_equal(first, again)
    assert first.shape != other.shape or not np.allclose(first, other)


def test_reset_with_the_same_seed_repeats_the_traffic_in_one_env():
    env = NeighbourhoodEnv(TOPDOWN)
    runs = []
    for _ in range(2):
        env.reset(seed=11, options={"start_index": 2})
        driver = PrivilegedDriver(TOPDOWN, seed=11)
        driver.reset(env.pose)
        runs.append(np.array([env.traffic.rectangles() for _ in drive(env, driver, 60)]))
    assert len(runs[0]) == 60 and np.array_equal(runs[0], runs[1])


# --- collisions --------------------------------------------------------------------------------

def test_driving_into_a_traffic_car_ends_the_episode_as_a_collision():
    env = NeighbourhoodEnv(ONE)
    env.reset(seed=0, options={"start_set": "train", "start_index": 0})  # A1 -> B1, clear ahead
    park(env.traffic.vehicles[0], *ahead_of(env, 12.0))
    for step in range(1, 40):
        _, reward, terminated, truncated, info = env.step(STRAIGHT)
        if terminated:
            break
    assert info["end"] == "collision" and info["collision"] and reward == 0.0 and not truncated
    assert 3 <= step <= 12  # reached after about (12 - 4.5) m at 10 m/s
    x, y, heading = env.pose
    assert not env.hood.obstacles.hits(x, y, heading, layout.CAR_LENGTH_M, layout.CAR_WIDTH_M)


def test_a_traffic_car_alongside_in_its_lane_is_no_collision():
    env = NeighbourhoodEnv(ONE)
    env.reset(seed=0, options={"start_set": "train", "start_index": 0})
    x, y, heading = ahead_of(env, 10.0, right=-ONE.lane_offset_m)  # in the oncoming lane, 0.2 m from us
    park(env.traffic.vehicles[0], x, y, heading + math.pi)
    for _ in range(20):
        *_, terminated, _, info = env.step(STRAIGHT)
        assert not terminated, info["end"]


# --- cameras -----------------------------------------------------------------------------------

def observation_with_car(env: NeighbourhoodEnv, metres: float | None) -> np.ndarray:
    """The observation at the present pose, the traffic car ``metres`` ahead (None: far away)."""
    park(env.traffic.vehicles[0], *(ahead_of(env, metres) if metres is not None else (*FAR_AWAY, 0.0)))
    return env.place(*env.pose)


def test_traffic_appears_in_the_topdown_frame():
    env = NeighbourhoodEnv(ONE)
    env.reset(seed=0, options={"start_index": 0})
    without = observation_with_car(env, None)
    with_car = observation_with_car(env, 15.0)
    assert not (without == TRAFFIC_CAR).all(axis=-1).any()
    assert (with_car == TRAFFIC_CAR).all(axis=-1).sum() > 20


@pytest.mark.skipif(importlib.util.find_spec("actor.sim.front_camera") is None, reason="no front camera yet")
def test_traffic_changes_the_front_frame_ahead_and_not_behind():
    env = NeighbourhoodEnv(EnvConfig(camera="front", traffic_vehicles=1))
    env.reset(seed=0, options={"start_index": 0})
    without = observation_with_car(env, None)
    assert not np.array_equal(observation_with_car(env, 15.0), without)
    assert np.array_equal(observation_with_car(env, -8.0), without)


# --- highway-env's observations ----------------------------------------------------------------

def observed_with_car_ahead(observation: dict, metres: float = 12.0, right: float = 0.0):
    """(What the observation type sees of one traffic car ahead of the ego car, the env), after
    a drive with moving traffic."""
    env = NeighbourhoodEnv(TOPDOWN, observation=observation)
    env.reset(seed=0, options={"start_set": "train", "start_index": 0})
    driver = PrivilegedDriver(TOPDOWN, seed=0)
    driver.reset(env.pose)
    for _ in drive(env, driver, 30):  # the traffic moving, every car's lane index changing
        assert env.observation_space.contains(env.observation_type.observe())
    for vehicle in env.traffic.vehicles:
        park(vehicle, *FAR_AWAY, 0.0)
    park(env.traffic.vehicles[0], *ahead_of(env, metres, right))
    return env.observation_type.observe(), env


def test_highway_env_kinematics_sees_the_traffic():
    seen, env = observed_with_car_ahead({"type": "Kinematics", "include_obstacles": False,
                                         "normalize": False, "absolute": False})
    assert env.observation_space.contains(seen)
    presence, x, y = seen[1, :3]
    assert presence == 1 and abs(math.hypot(x, y) - 12.0) < 0.5  # the car 12 m ahead, next row to the ego


def test_highway_env_occupancy_grid_sees_the_traffic():
    config = {"type": "OccupancyGrid", "features": ["presence"], "grid_size": [[-20, 20], [-20, 20]],
              "grid_step": [2, 2], "absolute": False, "align_to_vehicle_axes": True}
    seen, env = observed_with_car_ahead(config, metres=13.0, right=1.0)
    assert env.observation_space.contains(seen)
    assert seen[0, 16, 10] == 1  # the cell 13 m ahead and 1 m right of the ego car, in its frame
    assert seen[0, 10, 10] == 1 and seen.sum() == 2  # and the ego car itself

def test_highway_env_time_to_collision_sees_a_slow_car_on_the_ego_lane():
    env = NeighbourhoodEnv(ONE, observation={"type": "TimeToCollision", "horizon": 5})
    env.reset(seed=0, options={"start_set": "train", "start_index": 0})
    empty = env.observation_type.observe()
    lane = env.vehicle.lane_index
    u = env.road.network.get_lane(lane).local_coordinates(env.vehicle.position)[0]
    env.traffic.vehicles[0].place(lane, u + 12.0, 0.5)  # ahead on the ego car's lane, nearly stopped
    seen = env.observation_type.observe()
    assert np.all(np.isfinite(seen)) and seen.max() > 0 and not np.array_equal(seen, empty)


# --- giving way --------------------------------------------------------------------------------

def test_a_traffic_car_gives_way_before_a_narrow_passage_while_the_ego_car_comes_through():
    """C3-D3 has a car parked at the eastbound kerb 50 m from C3: an eastbound traffic car passes it
    across the centre-line, so it holds back while the westbound ego car comes through, then goes on."""
    env = NeighbourhoodEnv(ONE)
    env.reset(seed=0, options={"start_set": "train", "start_index": 7})  # D3 -> C3
    traffic = env.traffic
    car = traffic.vehicles[0]
    lane = ("C3>D3", "D3<C3", 0)
    car.place(lane, 5.0, 8.0)
    env.place(200.0, 140.0, math.pi)  # westbound on the centre-line, 15 m from D3
    driver = PrivilegedDriver(env.env_config, seed=0)
    driver.reset(env.pose)
    stretch = traffic.shapes[lane].stretches[0]  # where the car leaves its lane to pass
    street_start = env.hood.junctions["C3"][0] + layout.TURN_RADIUS_M  # x of the lane's start
    speeds, fronts = [], []
    for info in drive(env, driver, 150):
        on_lane = car.target_lane_index == lane
        fronts.append(traffic.shapes[lane].local(car.position)[0] + car.LENGTH / 2 if on_lane else math.inf)
        speeds.append(car.speed)
        if env.pose[0] + car.LENGTH > street_start + stretch[0]:  # the ego car by the stretch, or coming
            assert fronts[-1] < stretch[0]
    assert info["end"] is None
    assert min(speeds) < 0.5 * 8.0  # it held back
    assert fronts[-1] > stretch[1]  # and went on once the way was clear


def test_traffic_cars_take_turns_in_a_junction():
    """No two traffic cars are ever in the same junction area at once."""
    env, driver = started(BUSY, seed=5)
    traffic = env.traffic
    for _ in drive(env, driver, 400):
        inside = [traffic.shapes[v.target_lane_index].index for v in traffic.vehicles
                  if not is_street(v.target_lane_index)]
        junctions = [index[0].split("<")[0] for index in inside]
        assert len(junctions) == len(set(junctions)), junctions


# --- feasibility (the slow ones: about 10,000 steps each) --------------------------------------

@pytest.mark.parametrize("starts", [range(0, 5), range(5, 10)], ids=["0-4", "5-9"])
@pytest.mark.parametrize("start_set", ["train", "test"])
def test_privileged_driver_drives_full_episodes_with_traffic_from_every_start(start_set, starts):
    for index in starts:
        env, driver = started(TOPDOWN, seed=index, start_set=start_set, index=index)
        for info in drive(env, driver, TOPDOWN.max_steps):
            pass
        assert info["end"] == "cap" and info["step"] == TOPDOWN.max_steps, (start_set, index, info["end"])
        assert info["progress_m"] > 0.9 * TOPDOWN.max_steps * TOPDOWN.speed / TOPDOWN.policy_frequency


def test_too_little_room_drives_with_the_cars_that_fit_instead_of_raising(caplog):
    import dataclasses
    from actor.sim.traffic import Traffic, TrafficVehicle
    env = NeighbourhoodEnv(EnvConfig(camera="topdown", traffic_vehicles=1))
    crowded = dataclasses.replace(env.env_config, traffic_vehicles=60)  # more than the streets hold
    env.traffic = Traffic(env.road, crowded, env.vehicle)
    placed = []
    for seed in range(5):
        env.reset(seed=seed, options={"start_index": 0})
        on_road = [v for v in env.road.vehicles if isinstance(v, TrafficVehicle)]
        assert on_road == env.traffic.vehicles and len(env.traffic_rectangles()) == len(on_road)
        placed.append(len(on_road))
    assert 0 < min(placed) < 60
    assert "room for only" in caplog.text
