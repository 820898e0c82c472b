"""Plane geometry for one car against many fixed things, vectorised with numpy.

Everything the simulator asks each step (how far is the car from the nearest
centre-line; does the car's rectangle touch a parked car, a tree or a house)
is one pass over precomputed arrays, never a Python loop over objects.
"""

from __future__ import annotations

import math

import numpy as np


def unit(heading: float) -> tuple[float, float]:
    return math.cos(heading), math.sin(heading)


def right_of(heading: float) -> tuple[float, float]:
    """Unit vector to the driver's right in the y-down frame (heading + 90 degrees)."""
    return -math.sin(heading), math.cos(heading)


def arc_points(corner: np.ndarray, away_1: np.ndarray, away_2: np.ndarray, radius: float,
               pieces: int) -> np.ndarray:
    """Points of the quarter circle tangent to two perpendicular streets meeting at ``corner``.

    ``away_1`` and ``away_2`` are the unit directions of the streets leaving the
    corner. The arc runs from ``corner + radius * away_1`` to
    ``corner + radius * away_2`` around the centre ``corner + radius * (away_1 + away_2)``.
    """
    centre = corner + radius * (away_1 + away_2)
    t = np.linspace(0.0, math.pi / 2, pieces + 1)[:, None]
    return centre - radius * (np.cos(t) * away_2 + np.sin(t) * away_1)


def rectangle_corners(rectangles: np.ndarray) -> np.ndarray:
    """Rows (x, y, heading, length, width) to corners (n, 4, 2), in drawing order."""
    rectangles = np.asarray(rectangles, dtype=np.float64).reshape(-1, 5)
    x, y, heading, length, width = rectangles.T
    along = np.stack([np.cos(heading), np.sin(heading)], axis=1) * (length / 2)[:, None]
    across = np.stack([-np.sin(heading), np.cos(heading)], axis=1) * (width / 2)[:, None]
    centre = np.stack([x, y], axis=1)
    return np.stack([centre + along + across, centre + along - across,
                     centre - along - across, centre - along + across], axis=1)


class Segments:
    """A fixed set of line segments and the distance from a point to the nearest one."""

    def __init__(self, starts: np.ndarray, ends: np.ndarray) -> None:
        self.starts = np.asarray(starts, dtype=np.float64)
        self.ends = np.asarray(ends, dtype=np.float64)
        self.deltas = self.ends - self.starts
        lengths2 = np.einsum("ij,ij->i", self.deltas, self.deltas)
        if np.any(lengths2 <= 0):
            raise ValueError("segments must have a positive length")
        self.inverse_lengths2 = 1.0 / lengths2

    def __len__(self) -> int:
        return len(self.starts)

    def distance(self, x: float, y: float) -> float:
        """Distance from (x, y) to the nearest segment."""
        return math.sqrt(float(np.min(self.squared_distances(x, y))))

    def nearest(self, x: float, y: float) -> tuple[int, float, float]:
        """(index of the nearest segment, where along it from 0 to 1, distance to it)."""
        t, squared = self._projections(x, y)
        index = int(np.argmin(squared))
        return index, float(t[index]), math.sqrt(float(squared[index]))

    def squared_distances(self, x: float, y: float) -> np.ndarray:
        """Squared distance from (x, y) to each segment."""
        return self._projections(x, y)[1]

    def _projections(self, x: float, y: float) -> tuple[np.ndarray, np.ndarray]:
        """Per segment: where (x, y)'s nearest point lies along it (0 to 1), and the squared gap."""
        rel_x = x - self.starts[:, 0]
        rel_y = y - self.starts[:, 1]
        t = (rel_x * self.deltas[:, 0] + rel_y * self.deltas[:, 1]) * self.inverse_lengths2
        np.clip(t, 0.0, 1.0, out=t)
        gap_x = rel_x - t * self.deltas[:, 0]
        gap_y = rel_y - t * self.deltas[:, 1]
        return t, gap_x * gap_x + gap_y * gap_y


class Obstacles:
    """Fixed oriented rectangles and circles, and whether a car's rectangle touches any.

    A bounding-circle pre-check over all obstacles usually leaves none; the
    few that remain get the exact test (separating axes for rectangles, the
    clamped nearest point for circles).
    """

    def __init__(self, rectangles: np.ndarray, circles: np.ndarray) -> None:
        """``rectangles``: rows (x, y, heading, length, width); ``circles``: rows (x, y, radius)."""
        rectangles = np.asarray(rectangles, dtype=np.float64).reshape(-1, 5)
        circles = np.asarray(circles, dtype=np.float64).reshape(-1, 3)
        self.n_rectangles = len(rectangles)
        self.rect_centres = rectangles[:, :2]
        self.rect_axes_u = np.stack([np.cos(rectangles[:, 2]), np.sin(rectangles[:, 2])], axis=1)
        self.rect_axes_v = np.stack([-np.sin(rectangles[:, 2]), np.cos(rectangles[:, 2])], axis=1)
        self.rect_half_length = rectangles[:, 3] / 2
        self.rect_half_width = rectangles[:, 4] / 2
        self.circle_centres = circles[:, :2]
        self.circle_radius = circles[:, 2]
        centres = np.concatenate([self.rect_centres, self.circle_centres])
        self.xs, self.ys = centres[:, 0].copy(), centres[:, 1].copy()
        self.bounds = np.concatenate([np.hypot(self.rect_half_length, self.rect_half_width),
                                      self.circle_radius])

    def hits(self, x: float, y: float, heading: float, length: float, width: float) -> bool:
        """Whether the car rectangle centred at (x, y) overlaps any obstacle."""
        half_length, half_width = length / 2, width / 2
        reach = self.bounds + math.hypot(half_length, half_width)
        near = np.flatnonzero((self.xs - x) ** 2 + (self.ys - y) ** 2 < reach * reach)
        if len(near) == 0:
            return False
        car_u, car_v = np.array(unit(heading)), np.array(right_of(heading))
        rectangles = near[near < self.n_rectangles]
        circles = near[near >= self.n_rectangles] - self.n_rectangles
        return (_rectangles_hit(self, rectangles, x, y, car_u, car_v, half_length, half_width)
                or _circles_hit(self, circles, x, y, car_u, car_v, half_length, half_width))


def _rectangles_hit(obstacles: Obstacles, index: np.ndarray, x: float, y: float, car_u: np.ndarray,
                    car_v: np.ndarray, half_length: float, half_width: float) -> bool:
    """Separating-axis test of the car against the rectangles ``index``."""
    if len(index) == 0:
        return False
    offsets = obstacles.rect_centres[index] - (x, y)
    axes_u, axes_v = obstacles.rect_axes_u[index], obstacles.rect_axes_v[index]
    half_l, half_w = obstacles.rect_half_length[index], obstacles.rect_half_width[index]
    separated = np.zeros(len(index), dtype=bool)
    # On the car's axes its own extent is fixed and the obstacle's projects.
    for axis, car_extent in ((car_u, half_length), (car_v, half_width)):
        reach = car_extent + half_l * np.abs(axes_u @ axis) + half_w * np.abs(axes_v @ axis)
        separated |= np.abs(offsets @ axis) > reach
    # On each obstacle's axes the car's extent projects.
    for axes, own_extent in ((axes_u, half_l), (axes_v, half_w)):
        reach = own_extent + half_length * np.abs(axes @ car_u) + half_width * np.abs(axes @ car_v)
        separated |= np.abs(np.einsum("ij,ij->i", offsets, axes)) > reach
    return bool((~separated).any())


def _circles_hit(obstacles: Obstacles, index: np.ndarray, x: float, y: float, car_u: np.ndarray,
                 car_v: np.ndarray, half_length: float, half_width: float) -> bool:
    """Whether the circles ``index`` reach inside the car: nearest point of the rectangle."""
    if len(index) == 0:
        return False
    offsets = obstacles.circle_centres[index] - (x, y)
    gap_along = np.maximum(np.abs(offsets @ car_u) - half_length, 0.0)
    gap_across = np.maximum(np.abs(offsets @ car_v) - half_width, 0.0)
    return bool((gap_along ** 2 + gap_across ** 2 < obstacles.circle_radius[index] ** 2).any())
