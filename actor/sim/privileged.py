"""A scripted driver that sees the map: the simulator's proof of feasibility and a baseline.

It knows the road geometry and where every parked car is (privileged state no
learning agent gets). It plans a route junction by junction (a random turn
from a seeded RNG at each junction, never a U-turn; or, with ``turns`` "right"
or "left", always the way furthest to that side, which goes round one loop of
the grid for ever), lays a reference path
along the centre-lines and corner curves, shifts that path sideways around
parked cars that reach into the driving line, and follows it with pure
pursuit. Given the traffic cars' rectangles, it also moves over, by up to
``TRAFFIC_SHIFT_M``, to keep ``TRAFFIC_CLEARANCE_M`` from those beside its way
ahead: traffic keeps only 0.2 m from a car on the centre-line, and waits
close to the corners this car may swing wide of. The continuous steering it
wants is turned into the five discrete actions by error diffusion: the
rounding error of each step is carried into the next, so the average
steering is the wanted one.
"""

from __future__ import annotations

import math

import numpy as np

from actor.sim import layout
from actor.sim.env import STEERING_LEVELS
from actor.sim.geometry import Segments, rectangle_corners, right_of
from actor.sim.neighbourhood import Neighbourhood, Street, neighbourhood
from common.sim_config import EnvConfig

SPACING_M = 0.5  # between reference path points
LOOKAHEAD_M = 7.0
PLAN_AHEAD_M = 60.0  # keep at least this much path ahead of the car
CLEARANCE_M = 0.7  # kept between the car's side and a parked car
SWERVE_RAMP_M = 10.0  # distance over which the path moves sideways and back
SWERVE_EARLY_M = 5.0  # the path is fully aside this far before a parked car
SEARCH_M = 20.0  # how far ahead of the last match the nearest path point is sought
TRAFFIC_CLEARANCE_M = 0.6  # kept between the car's side and a traffic car beside its way
TRAFFIC_SHIFT_M = 0.6  # the most the path moves over for traffic
TRAFFIC_AHEAD_M = 20.0  # traffic this far along the path ahead is looked at
TRAFFIC_RAMP_M = 6.0  # over which the move for traffic fades in and out
TURNS = ("random", "right", "left")  # how the route goes on at a junction


class PrivilegedDriver:
    def __init__(self, env_config: EnvConfig, seed: int = 0, turns: str = "random") -> None:
        if turns not in TURNS:
            raise ValueError(f"turns: one of {TURNS}, got {turns!r}")
        self.config = env_config
        self.turns = turns
        self.hood: Neighbourhood = neighbourhood()
        self.rng = np.random.default_rng(seed)
        self.max_steering = math.radians(env_config.max_steer_deg)
        self.path = np.zeros((0, 2))
        self.index = 0  # of the path point nearest the car
        self.previous_leg: tuple[str, str] | None = None
        self.leg = self.next_leg = ("", "")  # (from junction, to junction)
        self.carry = 0.0

    def reset(self, pose: tuple[float, float, float]) -> None:
        """Starts a route from a pose on a street, driving the way the car faces."""
        self.previous_leg = None
        self.leg = self._street_under(pose)
        self.next_leg = (self.leg[1], self._next_junction(*self.leg))
        self.path = np.zeros((0, 2))
        self.index = 0
        self.carry = 0.0
        self._extend()
        self.index = self._nearest(pose, search_all=True)

    def act(self, pose: tuple[float, float, float], traffic: np.ndarray | None = None) -> int:
        """The action index for the car at ``pose``; ``traffic``: rows (x, y, heading, length, width)."""
        self.index = self._nearest(pose)
        while len(self.path) - self.index < PLAN_AHEAD_M / SPACING_M:
            self._extend()
        ahead = min(self.index + int(LOOKAHEAD_M / SPACING_M), len(self.path) - 1)
        target = self.path[ahead]
        if traffic is not None and len(traffic):
            target = target + self._traffic_shift(pose, np.asarray(traffic), ahead)
        wanted = pure_pursuit_steering(pose, target, layout.CAR_LENGTH_M) / self.max_steering
        return self._quantise(float(np.clip(wanted, -1.0, 1.0)))

    def _traffic_shift(self, pose, traffic: np.ndarray, ahead: int) -> np.ndarray:
        """The sideways move of the path point ``ahead`` that keeps clear of the traffic beside the way.

        Each traffic car's corners and side midpoints are placed on the path ahead (nearest point,
        offset to its right); one on the left pushes the path right until the car's side clears it
        by ``TRAFFIC_CLEARANCE_M``, one on the right pushes it left, over a car's length either side
        of it and a ramp beyond.
        """
        stop = min(self.index + int(TRAFFIC_AHEAD_M / SPACING_M), len(self.path) - 1)
        points = self.path[self.index:stop + 1]
        if len(points) < 2 or np.min(np.hypot(*(traffic[:, :2] - pose[:2]).T)) > TRAFFIC_AHEAD_M + 5.0:
            return np.zeros(2)
        tangents = np.gradient(points, axis=0)
        tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
        rights = np.stack([-tangents[:, 1], tangents[:, 0]], axis=1)
        corners = rectangle_corners(traffic)
        samples = np.concatenate([corners, (corners + np.roll(corners, 1, axis=1)) / 2], axis=1).reshape(-1, 2)
        gaps = samples[:, None, :] - points[None, :, :]
        nearest = np.argmin(np.einsum("ijk,ijk->ij", gaps, gaps), axis=1)
        offsets = np.einsum("ij,ij->i", samples - points[nearest], rights[nearest])
        keep_out = layout.CAR_WIDTH_M / 2 + TRAFFIC_CLEARANCE_M
        beside = (nearest > 0) & (nearest < len(points) - 1) & (np.abs(offsets) < keep_out)
        if not beside.any():
            return np.zeros(2)
        push = np.where(offsets[beside] < 0, offsets[beside] + keep_out, offsets[beside] - keep_out)
        along = nearest[beside] * SPACING_M  # of each sample, from the car's path point
        weight = _plateau(np.full(len(along), (ahead - self.index) * SPACING_M),
                          along - layout.CAR_LENGTH_M, along + layout.CAR_LENGTH_M, TRAFFIC_RAMP_M)
        right = float(np.max(np.maximum(push, 0.0) * weight, initial=0.0))
        left = float(np.min(np.minimum(push, 0.0) * weight, initial=0.0))
        shift = float(np.clip(right + left, -TRAFFIC_SHIFT_M, TRAFFIC_SHIFT_M))
        return shift * rights[min(ahead - self.index, len(points) - 1)]

    def _quantise(self, wanted: float) -> int:
        with_carry = wanted + self.carry
        action = int(np.argmin([abs(with_carry - level) for level in STEERING_LEVELS]))
        self.carry = float(np.clip(with_carry - STEERING_LEVELS[action], -0.5, 0.5))
        return action

    # --- route and path ------------------------------------------------------------------------

    def _street_under(self, pose) -> tuple[str, str]:
        x, y, heading = pose
        streets = Segments(np.array([st.start for st in self.hood.streets]),
                           np.array([st.end for st in self.hood.streets]))
        best = self.hood.streets[int(np.argmin(streets.squared_distances(x, y)))]
        facing = np.array([math.cos(heading), math.sin(heading)]) @ best.direction
        return (best.first, best.second) if facing >= 0 else (best.second, best.first)

    def _next_junction(self, previous: str, junction: str) -> str:
        choices = [j for j in self.hood.neighbours[junction] if j != previous]
        if self.turns == "random":
            return choices[int(self.rng.integers(len(choices)))]
        side = 1.0 if self.turns == "right" else -1.0
        return max(choices, key=lambda choice: side * self._turn_angle(previous, junction, choice))

    def _turn_angle(self, previous: str, junction: str, following: str) -> float:
        """How far the way from ``junction`` to ``following`` turns right of the way there from ``previous``
        (radians, negative to the left)."""
        coming = self.hood.street(previous, junction)
        going = self.hood.street(junction, following).direction
        return math.atan2(float(going @ np.array(right_of(coming.heading))), float(going @ coming.direction))

    def _extend(self) -> None:
        """Appends the current leg (with the corner that ends it) to the path; plans one more."""
        points = self._leg_points(self.previous_leg, self.leg, self.next_leg)
        keep_from = max(self.index - 10, 0)
        self.path = np.concatenate([self.path[keep_from:], points])
        self.index -= keep_from
        self.previous_leg, self.leg = self.leg, self.next_leg
        self.next_leg = (self.leg[1], self._next_junction(*self.leg))

    def _leg_points(self, previous_leg, leg, next_leg) -> np.ndarray:
        """Path points of ``leg``: its straight part, shifted round parked cars, then its corner."""
        street = self.hood.street(*leg)
        turned_in = previous_leg is not None and self.hood.turn(leg[0], previous_leg[0], leg[1])
        turn_out = self.hood.turn(leg[1], leg[0], next_leg[1])
        s_start = layout.TURN_RADIUS_M if turned_in else 0.0
        s_end = street.length - (layout.TURN_RADIUS_M if turn_out else 0.0)
        s = np.arange(s_start, s_end, SPACING_M)
        offsets = self._swerve_offsets(street, s)
        straight = street.start + s[:, None] * street.direction + offsets[:, None] * street.right
        if not turn_out:
            return straight
        return np.concatenate([straight, _densify(turn_out.points, SPACING_M)[:-1]])

    def _swerve_offsets(self, street: Street, s: np.ndarray) -> np.ndarray:
        """Sideways shift of the path (positive to the right) that keeps clear of parked cars."""
        keep_out = layout.CAR_WIDTH_M / 2 + CLEARANCE_M
        shift_left = np.zeros_like(s)  # <= 0
        shift_right = np.zeros_like(s)  # >= 0
        for car in self.hood.parked_cars:
            corners = rectangle_corners(np.array([car.rectangle]))[0] - street.start
            along, across = corners @ street.direction, corners @ street.right
            if along.max() < 0 or along.min() > street.length or np.abs(across).min() > 2 * keep_out + 3:
                continue
            weight = _plateau(s, along.min() - SWERVE_EARLY_M, along.max(), SWERVE_RAMP_M)
            if across.mean() > 0:  # parked on the right: pass on its left
                shift_left = np.minimum(shift_left, weight * min(across.min() - keep_out, 0.0))
            else:
                shift_right = np.maximum(shift_right, weight * max(across.max() + keep_out, 0.0))
        return shift_left + shift_right

    def _nearest(self, pose, search_all: bool = False) -> int:
        start = 0 if search_all else self.index
        stop = len(self.path) if search_all else min(self.index + int(SEARCH_M / SPACING_M), len(self.path))
        gaps = self.path[start:stop] - pose[:2]
        return start + int(np.argmin(np.einsum("ij,ij->i", gaps, gaps)))


def pure_pursuit_steering(pose: tuple[float, float, float], target: np.ndarray, length: float) -> float:
    """Steering angle (radians, positive right) whose arc takes the car's centre through ``target``."""
    x, y, heading = pose
    dx, dy = target[0] - x, target[1] - y
    forward = math.cos(heading) * dx + math.sin(heading) * dy
    across = -math.sin(heading) * dx + math.cos(heading) * dy
    distance2 = forward * forward + across * across
    if distance2 < 1e-9:
        return 0.0
    curvature = 2.0 * across / distance2
    # In highway-env's bicycle model (Vehicle.step) the centre's path has curvature
    # sin(beta) / (length / 2), with slip angle beta = atan(tan(steering) / 2).
    sin_beta = float(np.clip(curvature * length / 2, -0.99, 0.99))
    return math.atan(2.0 * math.tan(math.asin(sin_beta)))


def _plateau(s: np.ndarray, begin: float, end: float, ramp: float) -> np.ndarray:
    """1 on [begin, end], falling smoothly to 0 within ``ramp`` either side."""
    outside = np.maximum(np.maximum(begin - s, s - end), 0.0) / ramp
    t = np.clip(1.0 - outside, 0.0, 1.0)
    return t * t * (3 - 2 * t)


def _densify(points: np.ndarray, spacing: float) -> np.ndarray:
    lengths = np.linalg.norm(np.diff(points, axis=0), axis=1)
    along = np.concatenate([[0.0], np.cumsum(lengths)])
    s = np.arange(0.0, along[-1] + 1e-9, spacing)
    return np.stack([np.interp(s, along, points[:, 0]), np.interp(s, along, points[:, 1])], axis=1)
