"""The static world drawn once, with OpenCV, into one big RGB image.

Roads, kerbs, pavements, centre-line dashes, parked cars, trees and houses
never move, so each top-down camera frame is only a warp of this image (see
``camera.py``). The perspective camera (``front_camera.py``) warps the ground
alone (``ground_image``: the same picture without the objects, which it draws
standing up instead). Pixel (column c, row r) has its centre at world point
(x_min + (c + 0.5) / scale, y_min + (r + 0.5) / scale); y grows downwards on
the map as in the image.

The road surface is exactly the set of points within ``road_half_width`` of a
centre-line: each centre-line segment is drawn as a line that thick, with
round ends, so what the camera shows as road is where the car is on the road.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import cv2
import numpy as np

from actor.sim.geometry import rectangle_corners
from actor.sim.neighbourhood import Neighbourhood, neighbourhood

# RGB colours, chosen to stay distinct after conversion to grey as well.
GRASS = (96, 146, 70)
PAVEMENT = (176, 170, 158)
KERB = (222, 222, 216)
ASPHALT = (70, 70, 76)
CENTRE_DASH = (236, 204, 52)
PARKED_CAR = (204, 36, 36)
TREE = (26, 82, 34)
TREE_EDGE = (16, 56, 22)
HOUSE = (150, 96, 72)
HOUSE_EDGE = (104, 66, 50)
EGO_CAR = (40, 104, 232)
TRAFFIC_CAR = (236, 236, 240)  # white, far from the red of parked cars

# Only the perspective camera's: what stands up, and the air around it.
SKY = (112, 162, 226)  # at the top of the frame
HAZE = (196, 208, 218)  # at the horizon, and what the ground fades into beyond the camera's range
HOUSE_WALL = (214, 194, 160)
HOUSE_ROOF = (132, 60, 46)
TRUNK = (104, 72, 44)
CANOPY = (44, 112, 44)

KERB_WIDTH_M = 0.3
PAVEMENT_WIDTH_M = 1.8
DASH_LENGTH_M = 3.0
DASH_GAP_M = 3.0
DASH_WIDTH_M = 0.3
DASH_CLEAR_OF_JUNCTION_M = 6.0
MARGIN_M = 40.0  # grass drawn around the junctions; the camera sees grass beyond it too
SUBPIXEL_BITS = 4  # cv2 drawing with 1/16 pixel precision


@dataclass(frozen=True)
class WorldImage:
    # (rows, columns, 4) uint8, read-only: RGB and an unused fourth channel
    # (always 0), because OpenCV warps four channels about twice as fast as three.
    pixels: np.ndarray
    x_min: float
    y_min: float
    scale: float  # pixels per metre

    @property
    def rgb(self) -> np.ndarray:
        return self.pixels[..., :3]

    def to_pixels(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 2) in metres to continuous pixel coordinates (column, row)."""
        return (np.asarray(points) - (self.x_min, self.y_min)) * self.scale - 0.5


@functools.lru_cache(maxsize=4)
def world_image(scale: float, road_half_width: float) -> WorldImage:
    """The neighbourhood at ``scale`` px/m; shared by every env of the process (read-only)."""
    hood = neighbourhood()
    world = _ground(hood, scale, road_half_width)
    _draw_rectangles(world, hood.houses, HOUSE, HOUSE_EDGE)
    _draw_rectangles(world, np.array([car.rectangle for car in hood.parked_cars]), PARKED_CAR, None)
    _draw_trees(world, hood)
    world.pixels.flags.writeable = False
    return world


@functools.lru_cache(maxsize=4)
def ground_image(scale: float, road_half_width: float) -> WorldImage:
    """Grass, roads, kerbs, pavements and dashes only, same frame as ``world_image`` (read-only)."""
    world = _ground(neighbourhood(), scale, road_half_width)
    world.pixels.flags.writeable = False
    return world


def _ground(hood: Neighbourhood, scale: float, road_half_width: float) -> WorldImage:
    x_min, y_min, x_max, y_max = hood.bounds(MARGIN_M)
    shape = (int(round((y_max - y_min) * scale)), int(round((x_max - x_min) * scale)), 4)
    world = WorldImage(np.zeros(shape, dtype=np.uint8), x_min, y_min, scale)
    world.rgb[:] = GRASS
    _draw_roads(world, hood, road_half_width)
    _draw_dashes(world, hood)
    return world


def _draw_roads(world: WorldImage, hood: Neighbourhood, half_width: float) -> None:
    segments = hood.centre_lines
    starts, ends = world.to_pixels(segments.starts), world.to_pixels(segments.ends)
    for colour, reach in ((PAVEMENT, half_width + KERB_WIDTH_M + PAVEMENT_WIDTH_M),
                          (KERB, half_width + KERB_WIDTH_M),
                          (ASPHALT, half_width)):
        thickness = max(1, int(round(2 * reach * world.scale)))
        for start, end in zip(starts, ends):
            cv2.line(world.pixels, _fixed(start), _fixed(end), colour, thickness,
                     cv2.LINE_8, SUBPIXEL_BITS)


def _draw_dashes(world: WorldImage, hood: Neighbourhood) -> None:
    thickness = max(1, int(round(DASH_WIDTH_M * world.scale)))
    for street in hood.streets:
        s = DASH_CLEAR_OF_JUNCTION_M
        while s + DASH_LENGTH_M <= street.length - DASH_CLEAR_OF_JUNCTION_M:
            start, end = world.to_pixels([street.point(s), street.point(s + DASH_LENGTH_M)])
            cv2.line(world.pixels, _fixed(start), _fixed(end), CENTRE_DASH, thickness,
                     cv2.LINE_8, SUBPIXEL_BITS)
            s += DASH_LENGTH_M + DASH_GAP_M


def _draw_rectangles(world: WorldImage, rectangles: np.ndarray, fill, edge) -> None:
    for corners in rectangle_corners(rectangles):
        polygon = _fixed(world.to_pixels(corners))
        cv2.fillConvexPoly(world.pixels, polygon, fill, cv2.LINE_8, SUBPIXEL_BITS)
        if edge is not None:
            cv2.polylines(world.pixels, [polygon], True, edge, max(1, int(world.scale // 4)),
                          cv2.LINE_8, SUBPIXEL_BITS)


def _draw_trees(world: WorldImage, hood: Neighbourhood) -> None:
    for x, y, radius in hood.trees:
        centre = _fixed(world.to_pixels((x, y)))
        pixels_radius = int(round(radius * world.scale * (1 << SUBPIXEL_BITS)))
        cv2.circle(world.pixels, centre, pixels_radius, TREE, -1, cv2.LINE_8, SUBPIXEL_BITS)
        cv2.circle(world.pixels, centre, pixels_radius, TREE_EDGE, max(1, int(world.scale // 4)),
                   cv2.LINE_8, SUBPIXEL_BITS)


def _fixed(points: np.ndarray) -> np.ndarray | tuple[int, int]:
    """Continuous pixel coordinates to cv2's fixed-point integers."""
    scaled = np.round(np.asarray(points) * (1 << SUBPIXEL_BITS)).astype(np.int32)
    return tuple(int(v) for v in scaled) if scaled.ndim == 1 else scaled
