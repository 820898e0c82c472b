"""Plane geometry for one car against many fixed things.

Everything the simulator asks each step (how far is the car from the nearest
centre-line; does the car's rectangle touch a parked car, a tree or a house)
is one pass over precomputed arrays, never a Python loop over objects. The two
asked every simulation frame are compiled loops (numba): over a few hundred
segments or obstacles a loop that stops early costs a few microseconds, where
the same pass as numpy expressions costs a dozen calls of about two each.
"""

from __future__ import annotations

import math

import numba
import numpy as np


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
        index, t, squared = _nearest_segment(self.starts, self.deltas, self.inverse_lengths2, x, y)
        return index, t, math.sqrt(squared)

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


NO_CIRCLES = np.zeros((0, 3))  # an Obstacles of rectangles only
NO_RECTANGLES = np.zeros((0, 5))  # an Obstacles of circles only


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
        self.rect_axes_u = np.stack([np.cos(rectangles[:, 2]), np.sin(rectangles[:, 2])], axis=1)
        self.rect_axes_v = np.stack([-np.sin(rectangles[:, 2]), np.cos(rectangles[:, 2])], axis=1)
        self.rect_half_length = rectangles[:, 3] / 2
        self.rect_half_width = rectangles[:, 4] / 2
        self.circle_radius = circles[:, 2].copy()
        centres = np.concatenate([rectangles[:, :2], circles[:, :2]])
        self.xs, self.ys = centres[:, 0].copy(), centres[:, 1].copy()
        self.bounds = np.concatenate([np.hypot(self.rect_half_length, self.rect_half_width),
                                      self.circle_radius])

    def hits(self, x: float, y: float, heading: float, length: float, width: float) -> bool:
        """Whether the car rectangle centred at (x, y) overlaps any obstacle."""
        return _any_hit(self.xs, self.ys, self.bounds, self.n_rectangles, self.rect_axes_u, self.rect_axes_v,
                        self.rect_half_length, self.rect_half_width, self.circle_radius, x, y,
                        math.cos(heading), math.sin(heading), length / 2, width / 2)


@numba.njit(cache=True)
def _nearest_segment(starts, deltas, inverse_lengths2, x, y):
    """(index, where along from 0 to 1, squared distance) of the segment nearest (x, y); the
    first of equally near ones."""
    best, best_t, best_squared = 0, 0.0, np.inf
    for i in range(len(starts)):
        rel_x, rel_y = x - starts[i, 0], y - starts[i, 1]
        t = min(max((rel_x * deltas[i, 0] + rel_y * deltas[i, 1]) * inverse_lengths2[i], 0.0), 1.0)
        gap_x, gap_y = rel_x - t * deltas[i, 0], rel_y - t * deltas[i, 1]
        squared = gap_x * gap_x + gap_y * gap_y
        if squared < best_squared:
            best, best_t, best_squared = i, t, squared
    return best, best_t, best_squared


@numba.njit(cache=True)
def _any_hit(xs, ys, bounds, n_rectangles, axes_u, axes_v, half_lengths, half_widths, circle_radius,
             x, y, cos_h, sin_h, half_length, half_width):
    """A bounding-circle pre-check over all obstacles, the exact test for the few that pass:
    separating axes for rectangles, the clamped nearest point for circles."""
    car_reach = math.hypot(half_length, half_width)
    # The car's axes: along its heading, and to its right (-sin, cos) in the y-down frame.
    car_u, car_v = (cos_h, sin_h), (-sin_h, cos_h)
    for i in range(len(xs)):
        offset_x, offset_y = xs[i] - x, ys[i] - y
        reach = bounds[i] + car_reach
        if offset_x * offset_x + offset_y * offset_y >= reach * reach:
            continue
        if i < n_rectangles:
            if _rectangle_hit(offset_x, offset_y, (axes_u[i, 0], axes_u[i, 1]), (axes_v[i, 0], axes_v[i, 1]),
                              half_lengths[i], half_widths[i], car_u, car_v, half_length, half_width):
                return True
        else:
            along = max(abs(offset_x * car_u[0] + offset_y * car_u[1]) - half_length, 0.0)
            across = max(abs(offset_x * car_v[0] + offset_y * car_v[1]) - half_width, 0.0)
            if along * along + across * across < circle_radius[i - n_rectangles] ** 2:
                return True
    return False


@numba.njit(cache=True)
def _rectangle_hit(offset_x, offset_y, axis_u, axis_v, half_l, half_w, car_u, car_v, half_length,
                   half_width):
    """Separating-axis test of the car against one rectangle at ``offset`` from it."""
    # On the car's axes its own extent is fixed and the obstacle's projects.
    for axis, extent in ((car_u, half_length), (car_v, half_width)):
        reach = extent + half_l * abs(_dot(axis_u, axis)) + half_w * abs(_dot(axis_v, axis))
        if abs(offset_x * axis[0] + offset_y * axis[1]) > reach:
            return False
    # On the obstacle's axes the car's extent projects.
    for axis, extent in ((axis_u, half_l), (axis_v, half_w)):
        reach = extent + half_length * abs(_dot(axis, car_u)) + half_width * abs(_dot(axis, car_v))
        if abs(offset_x * axis[0] + offset_y * axis[1]) > reach:
            return False
    return True


@numba.njit(cache=True)
def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1]
