"""The perspective front camera: frame format, sky and road, what is and is not in view."""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np
import pytest

from actor.sim import start_poses
from actor.sim.camera import FRAME_SHAPE
from actor.sim.front_camera import (AMBIENT, DIFFUSE, ONE, ROOF_RISE_M, SUBPIXEL_BITS, SUN, PerspectiveCamera,
                                   _fill_convex, _fill_disc, front_strip)
from actor.sim.neighbourhood import ParkedCar, neighbourhood
from actor.sim.world_image import ASPHALT, HOUSE_ROOF, HOUSE_WALL, ground_image
from common.sim_config import EnvConfig

CONFIG = EnvConfig()
START = start_poses("train")[0]  # A1 -> B1, 15 m along a straight street, heading east


@pytest.fixture(scope="module")
def ground():
    return ground_image(CONFIG.render_scale, CONFIG.offroad_distance)


@pytest.fixture(scope="module")
def camera(ground):
    return PerspectiveCamera(ground, neighbourhood())


@pytest.fixture(scope="module")
def empty_street(ground):
    """The neighbourhood without its parked cars, so that a test can place its own."""
    return PerspectiveCamera(ground, dataclasses.replace(neighbourhood(), parked_cars=()))


def ahead_of_start(forward: float, right: float = 0.0) -> tuple[float, float]:
    """The world point ``forward`` metres along the start heading and ``right`` metres to its right."""
    c, s = math.cos(START.heading), math.sin(START.heading)
    return START.x + forward * c - right * s, START.y + forward * s + right * c


def car_at(forward: float, right: float = 0.0) -> np.ndarray:
    """One mover row (x, y, heading, length, width) relative to the start pose."""
    return np.array([[*ahead_of_start(forward, right), START.heading, 4.5, 1.8]])


def with_parked_car(ground, forward: float, right: float = 0.0) -> PerspectiveCamera:
    street = neighbourhood().street("A1", "B1")
    s = float(np.dot(np.array(ahead_of_start(forward, right)) - street.start, street.direction))
    car = ParkedCar(street, s, right, 0.0)
    return PerspectiveCamera(ground, dataclasses.replace(neighbourhood(), parked_cars=(car,)))


def start_frame(camera: PerspectiveCamera, movers=None) -> np.ndarray:
    return camera.frame(START.x, START.y, START.heading, movers)


def changed_columns(frame: np.ndarray, reference: np.ndarray) -> np.ndarray:
    return np.flatnonzero((frame != reference).any(axis=2).any(axis=0))


def test_frame_is_a_new_uint8_rgb_array_of_the_observation_shape(camera):
    first, second = start_frame(camera), start_frame(camera)
    assert first.shape == FRAME_SHAPE and first.dtype == np.uint8
    first[:] = 0
    assert second.any() and not np.shares_memory(first, second)


def test_view_renders_the_same_camera_at_another_size(camera):
    picture = camera.view(START.x, START.y, START.heading, 400, 132)
    assert picture.shape == (132, 400, 3) and picture.dtype == np.uint8


def test_sky_above_and_road_below_on_a_straight_street(empty_street):
    frame = start_frame(empty_street)
    sky = empty_street.lens(*FRAME_SHAPE[1::-1]).background[0, 0, :3]
    assert sky[2] > sky[0]  # blue at the top
    # Above the far end of the street (the trees either side reach into the top row).
    assert (frame[0, 85:115] == sky).all()
    # The bottom row, 2.5 m ahead: asphalt either side of the centre-line.
    for column in (40, 160):
        assert np.abs(frame[-1, column].astype(int) - ASPHALT).max() <= 1


def test_a_parked_car_behind_leaves_the_frame_unchanged_one_ahead_changes_it(ground, empty_street):
    reference = start_frame(empty_street)
    np.testing.assert_array_equal(start_frame(with_parked_car(ground, -5.0)), reference)
    assert (start_frame(with_parked_car(ground, 15.0)) != reference).any()


def test_a_mover_behind_leaves_the_frame_unchanged_one_ahead_changes_it(empty_street):
    reference = start_frame(empty_street)
    np.testing.assert_array_equal(start_frame(empty_street, car_at(-5.0)), reference)
    assert (start_frame(empty_street, car_at(15.0)) != reference).any()
    np.testing.assert_array_equal(start_frame(empty_street, np.empty((0, 5))), reference)


def test_a_car_level_with_the_driver_is_outside_the_field_of_view(ground, empty_street):
    reference = start_frame(empty_street)
    # Kerb-parked, its front 0.75 m ahead of the camera: 66 degrees to the right.
    np.testing.assert_array_equal(start_frame(with_parked_car(ground, -1.5, 2.6)), reference)
    np.testing.assert_array_equal(start_frame(empty_street, car_at(-1.5, -2.6)), reference)


def test_a_car_being_passed_shows_only_at_the_frame_edge_on_its_side(ground, empty_street):
    # Centred 1 m ahead at the kerb: it reaches behind the camera, its front is in view.
    reference = start_frame(empty_street)
    columns = changed_columns(start_frame(with_parked_car(ground, 1.0, 2.6)), reference)
    assert len(columns) and columns.min() >= FRAME_SHAPE[1] * 3 // 4


def test_the_image_is_not_mirrored(empty_street):
    reference = start_frame(empty_street)
    right = changed_columns(start_frame(empty_street, car_at(15.0, 3.0)), reference)
    left = changed_columns(start_frame(empty_street, car_at(15.0, -3.0)), reference)
    middle = FRAME_SHAPE[1] / 2
    assert len(right) and right.min() > middle
    assert len(left) and left.max() < middle


def test_a_nearer_box_hides_a_farther_one_behind_it(empty_street):
    near, far = car_at(10.0), car_at(20.0)
    alone = start_frame(empty_street, near)
    assert (start_frame(empty_street, far) != start_frame(empty_street)).any()  # far would show
    np.testing.assert_array_equal(start_frame(empty_street, np.concatenate([near, far])), alone)
    np.testing.assert_array_equal(start_frame(empty_street, np.concatenate([far, near])), alone)


def test_a_house_is_drawn_with_its_wall_and_roof_colours(empty_street):
    # Standing on street A1-B1 at x = 20 m and facing south, the north wall of the
    # first house (x 14 to 35.5 m, from y = 14 m) is straight ahead, in shadow.
    pose = (20.0, 0.0, math.pi / 2)
    wall = np.rint(np.array(HOUSE_WALL) * AMBIENT)
    frame = empty_street.frame(*pose)
    assert (np.abs(frame[0, 90:110].astype(int) - wall) <= 1).all()
    # Its roof rises above the frame's crop: a taller view keeps the crop's centre and
    # shows it, sunlit (the north slope faces the sun, which is high in the south).
    tall = empty_street.view(*pose, 200, 200)
    slope = np.array([0.0, -ROOF_RISE_M, neighbourhood().houses[0, 4] / 2])
    roof = np.rint(np.array(HOUSE_ROOF) * (AMBIENT + DIFFUSE * SUN @ slope / np.linalg.norm(slope)))
    column = tall[:, 100].astype(int)
    roof_rows = np.flatnonzero((np.abs(column - roof) <= 1).all(axis=1))
    wall_rows = np.flatnonzero((np.abs(column - wall) <= 1).all(axis=1))
    assert len(roof_rows) and len(wall_rows) and roof_rows.max() < wall_rows.min()


def test_objects_beyond_the_range_are_not_drawn(empty_street):
    reference = start_frame(empty_street)
    assert (start_frame(empty_street, car_at(30.0)) != reference).any()
    np.testing.assert_array_equal(start_frame(empty_street, car_at(empty_street.range + 5.0)), reference)


def test_frames_are_deterministic(ground, camera):
    pose = (START.x + 3.0, START.y + 0.5, START.heading + 0.1)
    first = camera.frame(*pose, car_at(12.0))
    np.testing.assert_array_equal(camera.frame(*pose, car_at(12.0)), first)
    again = PerspectiveCamera(ground, neighbourhood())
    np.testing.assert_array_equal(again.frame(*pose, car_at(12.0)), first)


def test_front_strip_stacks_the_frames_of_its_poses(camera):
    poses = [(*ahead_of_start(d), START.heading) for d in (0.0, 4.0, 8.0)]
    strip = front_strip(camera, poses, gap=2)
    assert strip.shape == (3 * FRAME_SHAPE[0] + 2 * 2, FRAME_SHAPE[1], 3)
    np.testing.assert_array_equal(strip[:FRAME_SHAPE[0]], camera.frame(*poses[0]))


# --- the compiled fill against OpenCV's ------------------------------------------------------

def _within_a_pixel_of_an_edge(differing: np.ndarray, mask: np.ndarray) -> bool:
    """Whether every differing pixel has a neighbour (8-connected) on the other side of the edge."""
    grown = cv2.dilate(mask, np.ones((3, 3), np.uint8))
    shrunk = cv2.erode(mask, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
    return bool(((grown > shrunk) | ~differing).all())


@pytest.mark.parametrize("seed", range(20))
def test_a_filled_convex_polygon_matches_opencv_but_along_its_edges(seed):
    rng = np.random.default_rng(seed)
    angles = np.sort(rng.uniform(0.0, 2 * np.pi, size=rng.integers(3, 6)))
    centre, radius = rng.uniform([20, 10], [180, 56]), rng.uniform(2.0, 30.0)
    points = np.rint((centre + radius * np.column_stack([np.cos(angles), np.sin(angles)])) * ONE).astype(np.int64)
    ours, theirs = np.zeros(FRAME_SHAPE, np.uint8), np.zeros(FRAME_SHAPE, np.uint8)
    _fill_convex(ours, points[:, 0].copy(), points[:, 1].copy(), len(points), np.array([255, 255, 255]))
    cv2.fillConvexPoly(theirs, points.astype(np.int32), (255, 255, 255), cv2.LINE_8, SUBPIXEL_BITS)
    ours, theirs = ours[..., 0], theirs[..., 0]
    assert _within_a_pixel_of_an_edge(ours != theirs, theirs)
    assert abs(int(ours.astype(bool).sum()) - int(theirs.astype(bool).sum())) <= 0.25 * theirs.astype(bool).sum() + 10


@pytest.mark.parametrize("seed", range(20))
def test_a_filled_disc_matches_opencv_but_along_its_edge(seed):
    rng = np.random.default_rng(seed)
    cx, cy = (int(v) for v in np.rint(rng.uniform([0, 0], [200, 66]) * ONE))
    radius = int(rng.uniform(1.0, 25.0) * ONE)
    ours, theirs = np.zeros(FRAME_SHAPE, np.uint8), np.zeros(FRAME_SHAPE, np.uint8)
    _fill_disc(ours, cx, cy, radius, np.array([255, 255, 255]))
    cv2.circle(theirs, (cx, cy), radius, (255, 255, 255), cv2.FILLED, cv2.LINE_8, SUBPIXEL_BITS)
    ours, theirs = ours[..., 0], theirs[..., 0]
    assert _within_a_pixel_of_an_edge(ours != theirs, theirs)
    assert abs(int(ours.astype(bool).sum()) - int(theirs.astype(bool).sum())) <= 0.25 * theirs.astype(bool).sum() + 10


def test_fills_reaching_past_the_image_are_cut_at_its_border():
    image = np.zeros(FRAME_SHAPE, np.uint8)
    huge = np.array([-10 ** 9, 10 ** 9, 0], dtype=np.int64)
    _fill_convex(image, huge, np.array([-10 ** 9, -10 ** 9, 10 ** 9], dtype=np.int64), 3, np.array([1, 2, 3]))
    assert (image == (1, 2, 3)).all()
    _fill_disc(image, -100 * ONE, -100 * ONE, 10 * ONE, np.array([9, 9, 9]))
    assert (image == (1, 2, 3)).all()
