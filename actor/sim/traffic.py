"""Moving traffic: highway-env IDM vehicles on routes of their own, which give way to the ego car.

Each traffic car is a ``TrafficVehicle``, an ``IDMVehicle`` registered in
``road.vehicles`` (so highway-env's observations see it) that drives
highway-env's way: ``follow_road`` along a ``route`` of lanes drawn from
``road.np_random`` (re-seeded from the env's generator at each reset, so the
same seed gives the same traffic), its own target speed drawn from
[``traffic_speed_min``, ``traffic_speed_max``], the IDM acceleration formula
and the lateral loop of ``ControlledVehicle``'s controller, moved by
highway-env's ``Vehicle.step``. A directed street is a single-lane edge, so
there are no lane changes. What is ours:

* **Passing parked cars.** IDM alone would stop behind the parked cars that
  reach into a lane and jam every street within a minute. Instead each lane
  has a lateral target profile (``LaneShape``): zero on a clear lane,
  swerving smoothly round every parked car on the lane's own side, across the
  centre-line if need be; the steering tracks it, closed on the course (see
  ``TrafficVehicle.steering_control``). The cars passed this way are not IDM
  obstacles.
* **Giving way, so that a driver who cannot brake can survive.** Elsewhere a
  traffic car keeps to its lane, 0.2 m from the side of an ego car on the
  centre-line. Where that fails, it waits (IDM behind a virtual stopped car)
  unless its way is clear:

  - a *stretch* is where a street lane's traffic swerves round a parked car,
    or where an ego car swerving round one on the far side reaches into the
    lane. A traffic car enters a street's stretches only if no ego car can be
    beside it there, over the bounds of its own motion (free-road IDM at
    most; at least the same half a second later, no faster than a slower
    leader) and every way the ego car can be on that street: already on it,
    or entering at either end at the earliest time its constant speed allows
    along the shortest lane path;
  - a *junction* area is entered only if the ego car cannot be in it from
    the moment the traffic car could arrive until the moment it is surely
    out, with the ego car arriving by each arm at its earliest;
  - a car never waits where it would stand in a unit (a stretch or a
    junction area): units too close to stop between are checked and taken
    together, to the end (a way too long to check within ``HORIZON_S`` is
    not taken), and inside them the car keeps the pace it was checked for;
  - each car reserves every unit it takes for the time its bounds give, and
    no two cars' reservations of a unit overlap.

  The ego car's earliest arrival by an arm can only come later as it drives,
  and a later arrival by the same arm means a detour of a block or more, so
  a check once passed holds. On the streets where parked cars leave no room
  to wait, ways get long: routes turn into streets with room where they can,
  and a car kept waiting ``REROUTE_S`` tries another way.
* **Speed.** A traffic car's lane is its target lane (no 90-lane search),
  its leader is found on its own path among the other movers only (not
  with ``Road.neighbour_vehicles``' loop over every tree and house), and its
  leader and way are looked at every ``DECISION_S``; steering and IDM run
  every frame.

Not simulated: contact between traffic cars (IDM following and the
reservations keep them apart; nothing checks it), and traffic avoiding an
ego car that leaves the centre-line outside the stretches, beyond braking for
it as an IDM leader when it is on the traffic car's own path.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from highway_env.road.lane import AbstractLane, StraightLane
from highway_env.road.road import LaneIndex, Road, RoadNetwork
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.kinematics import Vehicle

from actor.sim import layout
from actor.sim.geometry import rectangle_corners
from actor.sim.neighbourhood import neighbourhood, street_name
from common.sim_config import EnvConfig

HALF_LENGTH = layout.CAR_LENGTH_M / 2
HALF_WIDTH = layout.CAR_WIDTH_M / 2
# Passing parked cars.
CLEAR_SIDE_M = 0.3  # between a traffic car's side and a parked car it passes
CLEAR_ENDS_M = 1.0  # fully aside this long before and after a parked car
RAMP_M = 7.0  # distance over which a traffic car moves aside, and back
PAD_M = 12.0  # a street lane's profile reaches this far beyond its ends, into the junction lanes
PROFILE_SPACING_M = 0.25
PATH_SPACING_M = 0.5
# Stretches and junctions.
SWERVE_M = 0.05  # a traffic car this far off its lane centre leaves the ego car less than its 0.2 m
EGO_CLEARANCE_M = 0.7  # what a careful ego car keeps from a parked car it passes
EGO_SWERVE_REACH_M = 13.0  # ... moving aside from that far before it and back within that far after
SIDE_MARGIN_M = 0.1  # less than the nominal 0.2 m between a traffic car's side and the ego car's
JUNCTION_ENTRY_M = 1.5  # a junction area reaches this far back into an arriving street lane
JUNCTION_EXIT_M = 4.0  # ... and this far into a leaving one, where a turning car's body has straightened
STOP_GAP_M = 1.5  # a waiting traffic car's front stays this far from what it waits for
CLEAR_M = 3.0  # a junction is left when the car's rear is this far beyond it
WAIT_BRAKING = 5.0  # m/s^2: a car waits between units far enough apart to stop in after leaving one
TIME_MARGIN_S = 1.0  # between the traffic car and the ego car, at either end of a passage
BESIDE_MARGIN_M = 2.0  # plus the ego car's travel in TIME_MARGIN_S, ahead and behind
DECIDE_M = 40.0  # a traffic car checks its way this close to it
LOCK_M = 25.0  # and takes it this close, so that others wait in time
RECHECK_S = 0.3  # a car's answer for its way is reused this long, except to take it
DECISION_S = 0.1  # leaders and the way are looked at this often; steering and IDM run every frame
REROUTE_S = 8.0  # a car kept waiting this long for the same way tries another
HORIZON_S = 40.0  # every passage is checked to its end, within this
TIME_STEP_S = 0.2  # of the motion bounds; the margins are far wider than a step's travel
SLACK_S = 0.5  # the cautious bound runs this far behind free-road IDM
# Leaders, routes and spawning.
HORIZON_M = 300.0  # of path ahead, for stretches and junctions
LEADER_M = 40.0
LEADER_SIDE_MARGIN_M = 0.2
JAM_GAP_M = 2.0  # bumper to bumper, stopped
ROUTE_LANES = 16
SPAWN_EGO_CLEARANCE_M = 30.0
SPAWN_SPACING_M = 12.0
SPAWN_BRAKING_M = 15.0  # room before a stretch or junction to brake in

Interval = tuple[float, float]


# --- lane profiles -----------------------------------------------------------------------------

@dataclass
class LaneShape:
    """One lane as traffic drives it: its lateral target profile, the path that gives, its stretches."""

    index: LaneIndex
    lane: AbstractLane
    u: np.ndarray  # profile sample positions along the lane, beyond its ends too
    offset: np.ndarray  # lateral target at u, metres to the right of the lane centre
    slope: np.ndarray  # d offset / du
    path_u: np.ndarray  # path points along [0, length]
    path_xy: np.ndarray  # (n, 2) world points of the profile
    stretches: tuple[Interval, ...] = ()  # where no ego car may be beside a car of this lane
    shared: tuple[Interval, ...] = ()  # the stretches and where the other direction's swerve reaches
    waitable: bool = True  # a street lane with room to wait between its stretches and junctions
    units: tuple[tuple[str, float, float], ...] = ()  # (resource, start, end) in lane coordinates
    _grid: tuple | None = None  # the profile as plain lists, for ``target``

    @property
    def length(self) -> float:
        return float(self.lane.length)

    def target(self, u: float) -> tuple[float, float]:
        """(lateral target, its slope) at ``u``, interpolated on the regular profile grid."""
        if self._grid is None:
            self._grid = (float(self.u[0]), float(self.u[1] - self.u[0]), self.offset.tolist(), self.slope.tolist())
        start, step, offset, slope = self._grid
        place = min(max((u - start) / step, 0.0), len(offset) - 1.000001)
        i = int(place)
        t = place - i
        return offset[i] + t * (offset[i + 1] - offset[i]), slope[i] + t * (slope[i + 1] - slope[i])

    def heading(self, u: float) -> float:
        """The lane's heading, straight on beyond its ends (highway-env's arcs would carry on curving:
        a car switches to its next lane 2.5 m early and would turn in too soon)."""
        return float(self.lane.heading_at(min(max(u, 0.0), self.length)))

    def local(self, position: np.ndarray) -> tuple[float, float]:
        """(along, lateral) lane coordinates; before the lane's start, on the tangent there."""
        u, lateral = self.lane.local_coordinates(position)
        if u >= 0.0 or isinstance(self.lane, StraightLane):
            return u, lateral
        heading = self.heading(0.0)
        gap = position - self.lane.position(0.0, 0.0)
        return (float(gap[0] * math.cos(heading) + gap[1] * math.sin(heading)),
                float(-gap[0] * math.sin(heading) + gap[1] * math.cos(heading)))


def _plateau(u: np.ndarray, begin: float, end: float, ramp: float) -> np.ndarray:
    """1 on [begin, end], falling smoothly to 0 within ``ramp`` either side."""
    outside = np.maximum(np.maximum(begin - u, u - end), 0.0) / ramp
    t = np.clip(1.0 - outside, 0.0, 1.0)
    return t * t * (3 - 2 * t)


@dataclass(frozen=True)
class _Side:
    """A parked car seen from a street lane: its extent along the lane and across the street
    (``y``, from the centre-line, growing towards the lane's own side)."""

    u: Interval
    y: Interval

    @property
    def own_side(self) -> bool:
        return sum(self.y) > 0


def _parked_sides(lane: StraightLane, lane_offset: float, parked: np.ndarray) -> list[_Side]:
    sides = []
    for corners in parked:
        relative = corners - lane.start
        u = relative @ lane.direction
        y = relative @ lane.direction_lateral + lane_offset
        if u.max() < -PAD_M - RAMP_M or u.min() > lane.length + PAD_M + RAMP_M or np.abs(y).min() > 6.0:
            continue
        sides.append(_Side((float(u.min()), float(u.max())), (float(y.min()), float(y.max()))))
    return sides


def _street_profile(lane: StraightLane, sides: list[_Side], lane_offset: float,
                    road_half_width: float) -> tuple[np.ndarray, np.ndarray]:
    """Lateral target over the lane's extended length: aside of every parked car on its own side."""
    u = np.arange(-PAD_M, lane.length + PAD_M + 1e-9, PROFILE_SPACING_M)
    offset = np.zeros_like(u)
    for side in (s for s in sides if s.own_side):
        need = min(side.y[0] - HALF_WIDTH - CLEAR_SIDE_M - lane_offset, 0.0)
        weight = _plateau(u, side.u[0] - HALF_LENGTH - CLEAR_ENDS_M, side.u[1] + HALF_LENGTH + CLEAR_ENDS_M,
                          RAMP_M)
        offset = np.minimum(offset, weight * need)
    centre = lane_offset + offset  # from the centre-line
    for side in (s for s in sides if not s.own_side):
        beside = (u >= side.u[0] - HALF_LENGTH) & (u <= side.u[1] + HALF_LENGTH)
        if np.any(centre[beside] - HALF_WIDTH < side.y[1] + CLEAR_SIDE_M):
            raise ValueError(f"traffic cannot pass between the parked cars near {side.u} m along {lane}")
    if np.any(centre - HALF_WIDTH < -road_half_width):
        raise ValueError(f"traffic would leave the road passing a parked car on {lane}")
    return u, offset


def _shape(index: LaneIndex, lane: AbstractLane, u: np.ndarray, offset: np.ndarray) -> LaneShape:
    path_u = np.linspace(0.0, lane.length, max(2, int(lane.length / PATH_SPACING_M) + 1))
    lateral = np.interp(path_u, u, offset)
    path_xy = np.array([lane.position(s, r) for s, r in zip(path_u, lateral)])
    return LaneShape(index, lane, u, offset, np.gradient(offset, u), path_u, path_xy)


def is_street(index: LaneIndex) -> bool:
    """Street lanes leave a junction area (node "B2>C2"); junction lanes leave a street ("B2<A2")."""
    return ">" in index[0]


def junction_of(index: LaneIndex) -> str:
    """The junction a junction lane crosses."""
    return index[0].split("<")[0]


def opposite(index: LaneIndex) -> LaneIndex:
    """The street lane of the other direction: ("B2>C2", "C2<B2") -> ("C2>B2", "B2<C2")."""
    a, b = index[0].split(">")
    return (f"{b}>{a}", f"{a}<{b}", index[2])


def lane_shapes(network: RoadNetwork, lane_offset: float, road_half_width: float) -> dict[LaneIndex, LaneShape]:
    """Every lane's profile and stretches; a junction lane carries on the ramps of the street lanes it joins."""
    parked = rectangle_corners(np.array([car.rectangle for car in neighbourhood().parked_cars]))
    shapes, sides = {}, {}
    indices = [(a, b, i) for a, tos in network.graph.items() for b, lanes in tos.items() for i in range(len(lanes))]
    for index in filter(is_street, indices):
        lane = network.get_lane(index)
        sides[index] = _parked_sides(lane, lane_offset, parked)
        shapes[index] = _shape(index, lane, *_street_profile(lane, sides[index], lane_offset, road_half_width))
    _add_stretches(shapes, sides, lane_offset)
    streets_into = {index[1]: index for index in shapes}
    streets_out_of = {index[0]: index for index in shapes}
    for index in (i for i in indices if not is_street(i)):
        lane = network.get_lane(index)
        before, after = shapes[streets_into[index[0]]], shapes[streets_out_of[index[1]]]
        u = np.arange(-PAD_M, lane.length + PAD_M + 1e-9, PROFILE_SPACING_M)
        offset = (np.interp(before.length + u, before.u, before.offset, left=0.0, right=0.0)
                  + np.interp(u - lane.length, after.u, after.offset, left=0.0, right=0.0))
        shapes[index] = _shape(index, lane, u, offset)
    return shapes


# --- stretches ---------------------------------------------------------------------------------

def _swerve_intervals(shape: LaneShape, threshold: float) -> list[Interval]:
    """Where the lane's traffic is more than ``threshold`` left of its lane centre, widened by half a
    car (the profile is where the car's centre goes; a stretch is where its body is)."""
    aside = shape.offset < -threshold
    edges = np.flatnonzero(np.diff(np.concatenate([[0], aside.astype(int), [0]])))
    return [(float(shape.u[a]) - HALF_LENGTH, float(shape.u[b - 1]) + HALF_LENGTH)
            for a, b in zip(edges[::2], edges[1::2])]


def _ego_swerve_intervals(sides: list[_Side], lane_offset: float) -> list[Interval]:
    """Where an ego car passing a parked car on the far side comes within reach of this lane."""
    inner_side = lane_offset - HALF_WIDTH - SIDE_MARGIN_M  # of the lane's traffic
    near = EGO_SWERVE_REACH_M + HALF_LENGTH
    return [(side.u[0] - near, side.u[1] + near) for side in sides
            if not side.own_side and side.y[1] + EGO_CLEARANCE_M + 2 * HALF_WIDTH > inner_side]


def _merged(intervals: list[Interval], length: float) -> tuple[Interval, ...]:
    """Overlapping intervals joined, clipped to [0, length] (beyond is a junction's)."""
    merged: list[list[float]] = []
    for a, b in sorted(intervals):
        a, b = max(a, 0.0), min(b, length)
        if b <= a:
            continue
        if merged and a <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    return tuple((a, b) for a, b in merged)


def _add_stretches(shapes: dict[LaneIndex, LaneShape], sides: dict[LaneIndex, list[_Side]],
                   lane_offset: float) -> None:
    """Each street lane's stretches, and its shared intervals: where an opposite car's swerve
    comes within reach of this lane's cars too (the two directions must then take turns)."""
    head_on = 2 * HALF_WIDTH + SIDE_MARGIN_M - 2 * lane_offset  # an opposite car this far aside reaches us
    for index, shape in shapes.items():
        length = shape.length
        mine = _swerve_intervals(shape, SWERVE_M) + _ego_swerve_intervals(sides[index], lane_offset)
        theirs = [(length - b, length - a) for a, b in _swerve_intervals(shapes[opposite(index)], -head_on)]
        shape.stretches = _merged(mine, length)
        shape.shared = _merged(mine + theirs, length)


# --- distances over the lane graph -------------------------------------------------------------

class NodeDistances:
    """Shortest driving distances between the lane graph's nodes (Floyd-Warshall, once)."""

    def __init__(self, network: RoadNetwork) -> None:
        nodes = sorted(set(network.graph) | {b for tos in network.graph.values() for b in tos})
        self.number = {name: n for n, name in enumerate(nodes)}
        distances = np.full((len(nodes), len(nodes)), np.inf)
        np.fill_diagonal(distances, 0.0)
        for a, tos in network.graph.items():
            for b, lanes in tos.items():
                distances[self.number[a], self.number[b]] = min(lane.length for lane in lanes)
        for k in range(len(nodes)):
            distances = np.minimum(distances, distances[:, k:k + 1] + distances[k:k + 1, :])
        self.distances = distances

    def between(self, a: str, b: str) -> float:
        return float(self.distances[self.number[a], self.number[b]])


# --- where the ego car can be ------------------------------------------------------------------

class EgoForecast:
    """Where the ego car can be, from its lane, place and constant speed; made for each decision.

    Street tracks are (start time, u at start, +1 or -1) in the coordinates of a
    given street lane: the ego car at ``u + direction * speed * (t - start)``
    from ``start`` on. Junction intervals are times the ego car's body can be in
    a junction area. On a junction lane the ego car's way out is unknown (its
    lane is only the nearest of several that start together), so distances from
    there are the least over every way out.
    """

    def __init__(self, ego: Vehicle, network: RoadNetwork, distances: NodeDistances,
                 junction_reach: dict[str, float]) -> None:
        self.index = ego.lane_index
        lane = network.get_lane(self.index)
        place = getattr(ego, "place", None)
        self.u = place.longitudinal if place is not None and place.index == self.index \
            else lane.local_coordinates(ego.position)[0]
        self.speed = max(float(ego.speed), 1e-6)
        self.distances, self.junction_reach = distances, junction_reach
        if is_street(self.index):
            self.node, self.to_go = self.index[1], lane.length - self.u
        else:
            self.node, self.to_go = self.index[0], -self.u

    def to_node(self, node: str) -> float:
        """Least driving distance from the ego car's centre to a node."""
        return max(self.to_go + self.distances.between(self.node, node), 0.0)

    def street_tracks(self, index: LaneIndex, length: float) -> list[tuple[float, float, float]]:
        back = opposite(index)
        tracks = [(self.to_node(index[0]) / self.speed, 0.0, 1.0),
                  (self.to_node(back[0]) / self.speed, length, -1.0)]
        if self.index == index:
            tracks.append((0.0, self.u, 1.0))
        elif self.index == back:
            tracks.append((0.0, length - self.u, -1.0))
        return tracks

    def junction_intervals(self, junction: str, arms: tuple[str, ...]) -> list[Interval]:
        reach = self.junction_reach[junction]  # from entering the area to the rear leaving it
        intervals = []
        for arm in arms:
            arrive = (self.to_node(f"{junction}<{arm}") - JUNCTION_ENTRY_M - HALF_LENGTH) / self.speed
            intervals.append((arrive, arrive + reach / self.speed))
        if not is_street(self.index) and junction_of(self.index) == junction:
            intervals.append((0.0, (reach - self.u) / self.speed))
        elif is_street(self.index) and self.index[0].split(">")[0] == junction \
                and self.u - HALF_LENGTH < JUNCTION_EXIT_M:
            intervals.append((0.0, (JUNCTION_EXIT_M + HALF_LENGTH - self.u) / self.speed))
        return intervals


# --- the vehicles ------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Leader:
    """What IDM's desired gap reads of the car ahead."""
    velocity: np.ndarray


STANDING = _Leader(np.zeros(2))
MAX_SLIP = math.atan(math.tan(IDMVehicle.MAX_STEERING_ANGLE) / 2)  # Vehicle.step's slip at full steering
TIMES = np.arange(0.0, HORIZON_S + 1e-9, TIME_STEP_S)


@dataclass
class _Bounds:
    """How far along its path a traffic car can be at the times ``TIMES``: at least, at most."""
    low: np.ndarray
    high: np.ndarray

    def first_time(self, distance: float, high: bool) -> float:
        """When the (high or low) bound first reaches ``distance``; inf beyond the horizon."""
        bound = self.high if high else self.low
        index = int(np.searchsorted(bound, distance))  # bounds never decrease
        return float(TIMES[index]) if index < len(TIMES) else math.inf


class TrafficVehicle(IDMVehicle):
    """An ``IDMVehicle`` that keeps to its route's lanes and tracks their lateral profiles."""

    LENGTH = layout.CAR_LENGTH_M
    WIDTH = layout.CAR_WIDTH_M
    DISTANCE_WANTED = layout.CAR_LENGTH_M + JAM_GAP_M  # centre to centre, stopped

    def __init__(self, road: Road, shapes: dict[LaneIndex, LaneShape], lane_index: LaneIndex, dt: float,
                 slowest: float) -> None:
        """``slowest``: the least target speed of any traffic car (a leader that joins its way)."""
        lane = road.network.get_lane(lane_index)
        super().__init__(road, lane.position(0.0, 0.0), lane.heading_at(0.0), 0.0,
                         target_lane_index=lane_index, enable_lane_change=False)
        self.shapes, self.dt, self.slowest = shapes, dt, slowest
        self.fronts: list[tuple[float, _Leader]] = []  # (centre-to-centre gap, leader), set by Traffic
        self.odometer = 0.0  # metres driven; the gaps in ``fronts`` shrink by what it drives after
        self.fronts_at = 0.0  # ... the odometer when they were measured
        self.waiting: str | None = None  # what the car last found in its way: a street, a junction...
        self.committed: set[tuple] = set()  # keys of the units it has checked and reserved
        self.lanes_done = 0  # lanes of its route left behind: units are keyed by route position
        self._local: tuple | None = None
        self.plan: tuple | None = None  # (route, lanes, units, end) from the start of its lane
        self.answer: tuple | None = None  # (first unit's key, time, clear) of its last check
        self.blocked: tuple | None = None  # (first unit's key, since when) of the way it waits for
        self.steps_per_time = int(round(TIME_STEP_S / dt))
        self.slack_steps = int(round(SLACK_S / dt))

    def place(self, lane_index: LaneIndex, u: float, speed: float) -> None:
        """Puts the car ``u`` metres along a lane, on its profile, at ``speed`` (its target too)."""
        lane = self.road.network.get_lane(lane_index)
        lateral, _ = self.shapes[lane_index].target(u)
        self.position = np.array(lane.position(u, lateral), dtype=np.float64)
        self.heading = float(lane.heading_at(u))
        self.speed = self.target_speed = speed
        self.target_lane_index = lane_index
        self.route = [lane_index]
        self.action = {"steering": 0.0, "acceleration": 0.0}
        self.crashed, self.timer, self.fronts, self.waiting = False, 0.0, [], None
        self.odometer = self.fronts_at = 0.0
        self.committed, self.plan, self.answer, self.blocked = set(), None, None, None
        self.lanes_done = 0
        self.randomize_behavior()
        self.extend_route()
        self.on_state_update()
        self.free_speed, self.free_distance = self._free_road(self.target_speed)
        self.slow_speed, self.slow_distance = self._free_road(min(self.target_speed, self.slowest))

    def _free_road(self, target: float) -> tuple[np.ndarray, np.ndarray]:
        """Speed and distance from a standstill on a free road towards ``target``, integrated as
        ``Vehicle.step`` does, long enough to run the whole horizon from any speed."""
        steps = 2 * (len(TIMES) * self.steps_per_time + self.slack_steps)
        speeds, distances = np.zeros(steps + 1), np.zeros(steps + 1)
        target = max(target, 1e-2)
        for k in range(steps):
            acceleration = self.COMFORT_ACC_MAX * (1 - (speeds[k] / target) ** self.DELTA)
            distances[k + 1] = distances[k] + speeds[k] * self.dt
            speeds[k + 1] = max(speeds[k] + acceleration * self.dt, 0.0)  # as idm_acceleration: no reversing
        return speeds, distances

    def bounds(self, leader_speed: float | None) -> _Bounds:
        """At most free-road IDM from the present speed; at least free-road IDM towards the slowest
        traffic's speed (a slower car may join its way ahead), ``SLACK_S`` later, and no faster
        than a slower leader."""
        high = _reach(self.free_speed, self.free_distance, self.speed, self.steps_per_time, 0)
        low = _reach(self.slow_speed, self.slow_distance, min(self.speed, self.slow_speed[-1]),
                     self.steps_per_time, self.slack_steps)
        if leader_speed is not None and leader_speed < self.target_speed:
            low = np.minimum(low, max(leader_speed, 0.0) * TIMES)
        return _Bounds(low, high)

    def follow_road(self) -> None:
        lane = self.target_lane_index
        super().follow_road()
        self.lanes_done += self.target_lane_index != lane

    def local(self) -> tuple[float, float]:
        """(along, lateral) on the target lane, computed once per position."""
        key = (self.target_lane_index, float(self.position[0]), float(self.position[1]))
        if self._local is None or self._local[0] != key:
            self._local = (key, self.shapes[self.target_lane_index].local(self.position))
        return self._local[1]

    def on_state_update(self) -> None:
        # The car's lane is the one it follows: no search over all 90 lanes.
        self.lane_index = self.target_lane_index
        self.lane = self.road.network.get_lane(self.lane_index)

    def extend_route(self) -> None:
        """highway-env's ``next_lane`` follows ``route``; this keeps it drawn ahead at random, turning
        into streets with room to wait in when there are any (elsewhere a car must get through a long
        run of stretches and junctions at once, which it seldom may)."""
        graph = self.road.network.graph
        while len(self.route) < ROUTE_LANES:
            _, end, _ = self.route[-1]
            onward = sorted(graph[end])
            roomy = [to for to in onward if self._street_after((end, to, 0)).waitable]
            choices = roomy or onward
            self.route.append((end, choices[int(self.road.np_random.integers(len(choices)))], 0))

    def _street_after(self, index: LaneIndex) -> LaneShape:
        """The lane itself if a street, else the street a junction lane leads into."""
        if is_street(index):
            return self.shapes[index]
        towards = index[1].split(">")[1]
        return self.shapes[(index[1], f"{towards}<{junction_of(index)}", 0)]

    def redraw_route(self, keep: int) -> None:
        """A new random route after its first ``keep`` lanes (at least the present one)."""
        del self.route[max(keep, 1):]
        self.extend_route()

    @property
    def wait_room(self) -> float:
        """How far apart two units must be for the car to stop between them after leaving the first."""
        return self.LENGTH + STOP_GAP_M + self.target_speed ** 2 / (2 * WAIT_BRAKING) + 1.0

    def act(self, action: dict | str | None = None) -> None:
        """Steers along the profile; accelerates by IDM behind ``self.fronts``."""
        self.follow_road()
        self.extend_route()
        Vehicle.act(self, {"steering": self.steering_control(self.target_lane_index),
                           "acceleration": self.idm_acceleration()})

    def idm_acceleration(self) -> float:
        """highway-env's IDM (``IDMVehicle.acceleration``) with gaps along the path; never reverses."""
        target = min(max(self.target_speed, 1e-2), self.lane.speed_limit or math.inf)
        free = self.COMFORT_ACC_MAX * (1 - (max(self.speed, 0.0) / target) ** self.DELTA)
        acceleration = free
        driven = self.odometer - self.fronts_at  # since the gaps were measured; leaders may have moved on
        for gap, leader in self.fronts:
            ratio = self._desired_gap(leader) / max(gap - driven, 1e-2)
            acceleration = min(acceleration, free - self.COMFORT_ACC_MAX * ratio * ratio)
        acceleration = min(max(acceleration, -self.ACC_MAX), self.ACC_MAX)
        return max(acceleration, -self.speed / self.dt)

    def _desired_gap(self, leader: _Leader) -> float:
        """``IDMVehicle.desired_gap`` (projected), in plain floats: it runs for every car every frame."""
        cos, sin = math.cos(self.heading), math.sin(self.heading)
        closing = self.speed - (float(leader.velocity[0]) * cos + float(leader.velocity[1]) * sin)
        braking = math.sqrt(-self.COMFORT_ACC_MAX * self.COMFORT_ACC_MIN)
        return self.DISTANCE_WANTED + self.speed * self.TIME_WANTED + self.speed * closing / (2 * braking)

    def steering_control(self, target_lane_index: LaneIndex) -> float:
        """``ControlledVehicle.steering_control``'s lateral loop on the profile instead of the lane
        centre, closed on the course rather than the heading.

        ``Vehicle.step`` moves the car's centre along heading + slip angle, and the slip angle
        follows the steering at once; so the steering that points the centre's course along the
        wanted course needs no heading loop, and does not cut corners (highway-env's heading
        loop runs a metre inside a 10 m corner and leaves it 0.2 rad late).
        """
        shape = self.shapes[target_lane_index]
        u, lateral = self.local() if target_lane_index == self.target_lane_index else shape.local(self.position)
        target, slope = shape.target(u)
        speed = max(abs(self.speed), 1e-2)
        lateral_speed_command = -self.KP_LATERAL * (lateral - target)
        heading_command = math.asin(min(max(lateral_speed_command / speed, -1.0), 1.0))
        course = shape.heading(u) + math.atan(slope) + min(max(heading_command, -math.pi / 4), math.pi / 4)
        slip = min(max(_wrap(course - self.heading), -MAX_SLIP), MAX_SLIP)
        return math.atan(2 * math.tan(slip))


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


def _reach(speeds: np.ndarray, distances: np.ndarray, speed: float, stride: int, delay: int) -> np.ndarray:
    """Distance covered by ``TIMES`` from ``speed`` along a free-road run (``speeds``, ``distances``
    every frame), ``delay`` frames late; ``stride`` frames per ``TIME_STEP_S``."""
    start = min(int(np.searchsorted(speeds, max(speed, 0.0))), len(speeds) // 2)
    steps = start + np.arange(len(TIMES)) * stride
    return distances[np.maximum(steps - delay, start)] - distances[start]


# --- the traffic -------------------------------------------------------------------------------

class _Unit(NamedTuple):
    """A junction area or a street's stretch on a traffic car's path, in path distances."""

    key: tuple  # the unit itself: (its lane's place on the route, where on the lane it starts)
    resource: str  # a junction's or a street's name: at most one traffic car in it at a time
    entry: float
    exit: float
    shape: LaneShape | None  # the street lane (None for a junction)
    begin: float  # path distance of the lane's start


@dataclass
class _Ahead:
    """A car's path ahead, in distances from the start of its lane; ``u`` is where the car is."""
    lanes: list[tuple[LaneShape, float]]  # the path's lanes and where each begins
    units: list[_Unit]
    end: float  # where the last lane ends
    u: float
    distances: np.ndarray  # of the path points within LEADER_M ahead, from the car
    points: np.ndarray  # (n, 2)

    def shifted(self, unit: _Unit) -> _Unit:
        """The unit in path distances from the car."""
        return unit._replace(entry=unit.entry - self.u, exit=unit.exit - self.u, begin=unit.begin - self.u)


class Traffic:
    """``config.traffic_vehicles`` traffic cars on ``road``, giving way to ``ego``."""

    def __init__(self, road: Road, config: EnvConfig, ego: Vehicle) -> None:
        self.road, self.ego = road, ego
        if not hasattr(ego, "route"):
            # highway-env's TimeToCollision reads the observer's planned route (a ControlledVehicle's)
            # once another vehicle is on its road; the ego car has none planned.
            ego.route = None
        self.speed_range = (config.traffic_speed_min, config.traffic_speed_max)
        self.shapes = lane_shapes(road.network, config.lane_offset_m, config.offroad_distance)
        self._add_units(config.traffic_speed_max)
        self.distances = NodeDistances(road.network)
        self.arms = {name: tuple(near) for name, near in neighbourhood().neighbours.items()}
        longest: dict[str, float] = {}
        for index, shape in self.shapes.items():
            if not is_street(index):
                longest[junction_of(index)] = max(longest.get(junction_of(index), 0.0), shape.length)
        self.junction_reach = {j: JUNCTION_ENTRY_M + length + JUNCTION_EXIT_M + layout.CAR_LENGTH_M
                               for j, length in longest.items()}
        self.reservations: dict[str, dict[TrafficVehicle, Interval]] = {}  # resource: car: sim-time window
        self.time = self.next_decision = 0.0
        self.spawn_places = self._spawn_places()
        dt = 1.0 / config.simulation_frequency
        first = next(iter(self.shapes))
        # Every car the config asks for; ``vehicles`` are those placed this episode.
        self.fleet = [TrafficVehicle(road, self.shapes, first, dt, config.traffic_speed_min)
                      for _ in range(config.traffic_vehicles)]
        self.vehicles = list(self.fleet)
        road.vehicles.extend(self.vehicles)
        self.forecast: EgoForecast | None = None

    def _add_units(self, fastest: float) -> None:
        """Each lane's units in its own coordinates, and whether a street lane has room to wait."""
        room = layout.CAR_LENGTH_M + STOP_GAP_M + fastest ** 2 / (2 * WAIT_BRAKING) + 1.0
        for index, shape in self.shapes.items():
            if is_street(index):
                name = street_name(*index[0].split(">"))
                shape.units = tuple((name, a, b) for a, b in shape.shared)
                shape.waitable = _has_room(shape, room)
            else:
                shape.units = ((junction_of(index), -JUNCTION_ENTRY_M, shape.length + JUNCTION_EXIT_M),)

    def _spawn_places(self) -> tuple[list[tuple[LaneIndex, float]], list[tuple[LaneIndex, float]]]:
        """Street lane places, outside junction areas: (clear of stretches with room to brake before
        the next, in a stretch)."""
        clear, inside = [], []
        for index, shape in self.shapes.items():
            if not is_street(index):
                continue
            first = JUNCTION_EXIT_M + CLEAR_M + HALF_LENGTH
            last = shape.length - JUNCTION_ENTRY_M - HALF_LENGTH - SPAWN_BRAKING_M
            for u in np.arange(first, last, 1.0):
                free = not any(a - HALF_LENGTH - SPAWN_BRAKING_M <= u <= b + HALF_LENGTH for a, b in shape.shared)
                (clear if free else inside).append((index, float(u)))
        return clear, inside

    # --- episode ---------------------------------------------------------------------------

    def reset(self, np_random: np.random.Generator) -> None:
        """New traffic for an episode: places, speeds and routes from ``np_random`` alone."""
        self.road.np_random = rng = np.random.default_rng(int(np_random.integers(2 ** 63)))
        self.reservations.clear()
        self.time = self.next_decision = 0.0
        ego = np.asarray(self.ego.position, dtype=np.float64)
        taken: list[np.ndarray] = []
        self.forecast = EgoForecast(self.ego, self.road.network, self.distances, self.junction_reach)
        for places in self.spawn_places:  # clear places first; in stretches if there are too few
            for place in rng.permutation(len(places)):
                if len(taken) == len(self.fleet):
                    break
                index, u = places[place]
                point = self.shapes[index].lane.position(u, 0.0)
                if np.linalg.norm(point - ego) < SPAWN_EGO_CLEARANCE_M \
                        or any(np.linalg.norm(point - other) < SPAWN_SPACING_M for other in taken):
                    continue
                vehicle = self.fleet[len(taken)]
                vehicle.place(index, u, float(rng.uniform(*self.speed_range)))
                if self._clear_to_start(vehicle):
                    taken.append(point)
        self._field(len(taken))

    def _field(self, placed: int) -> None:
        """The episode drives with the first ``placed`` cars; too little room is logged, not
        raised, so an unlucky draw cannot stop an actor or an evaluation."""
        if placed < len(self.fleet):
            logging.getLogger(__name__).warning(
                "traffic: room for only %d of %d cars this episode", placed, len(self.fleet))
        self.vehicles = self.fleet[:placed]
        others = [v for v in self.road.vehicles if not isinstance(v, TrafficVehicle)]
        self.road.vehicles[:] = others + self.vehicles

    def _clear_to_start(self, vehicle: TrafficVehicle) -> bool:
        """Whether a car may start where it is: the units it is in, and those too close after to
        wait before, pass the same checks as a way it would take."""
        ahead = self._ahead(vehicle)
        chain, last_exit = [], -math.inf
        for unit in (ahead.shifted(unit) for unit in ahead.units):
            if unit.exit <= -HALF_LENGTH:
                continue
            if unit.entry >= HALF_LENGTH and unit.entry - last_exit >= vehicle.wait_room:
                break
            chain.append(unit)
            last_exit = unit.exit
        return not chain or self._clear(vehicle, chain, None, vehicle.bounds(None), ahead.end - ahead.u)

    def rectangles(self) -> np.ndarray:
        """The traffic cars as rows (x, y, heading, length, width)."""
        return np.array([(v.position[0], v.position[1], v.heading, v.LENGTH, v.WIDTH) for v in self.vehicles],
                        dtype=np.float64).reshape(-1, 5)

    def step(self, dt: float) -> None:
        for vehicle in self.vehicles:
            vehicle.odometer += max(vehicle.speed, 0.0) * dt  # what Vehicle.step moves it
            vehicle.step(dt)
        self.time += dt

    # --- decisions -------------------------------------------------------------------------

    def act(self) -> None:
        """Every car's steering and acceleration for this frame; every ``DECISION_S`` its leader and
        its way first, car by car in a fixed order (which settles ties for units)."""
        if self.time >= self.next_decision - 1e-9:
            self.next_decision = self.time + DECISION_S
            for vehicle in self.vehicles:
                vehicle.follow_road()  # its lane and route as its act will see them
                vehicle.extend_route()
            self._decide_all()
        for vehicle in self.vehicles:
            vehicle.act()

    def _decide_all(self) -> None:
        self.forecast = EgoForecast(self.ego, self.road.network, self.distances, self.junction_reach)
        movers = [(v.position, v.velocity, v.WIDTH) for v in self.vehicles]
        movers.append((self.ego.position, self.ego.velocity, self.ego.WIDTH))
        for number, vehicle in enumerate(self.vehicles):
            ahead = self._ahead(vehicle)
            leader = self._leader(vehicle, ahead, movers[:number] + movers[number + 1:])
            vehicle.fronts = [] if leader is None else [leader]
            stop = self._way(vehicle, ahead, leader)
            if stop is not None:
                vehicle.fronts.append((stop + vehicle.DISTANCE_WANTED, STANDING))
            vehicle.fronts_at = vehicle.odometer

    def _ahead(self, vehicle: TrafficVehicle) -> _Ahead:
        """The car's lanes and units ahead, from its plan (redone when its route changes)."""
        route = (vehicle.lanes_done, *vehicle.route)
        if vehicle.plan is None or vehicle.plan[0] != route:
            vehicle.plan = (route, *self._plan(vehicle.route, vehicle.lanes_done))
        _, lanes, units, end, distances, points = vehicle.plan
        u = vehicle.local()[0]
        near = slice(int(np.searchsorted(distances, u)), int(np.searchsorted(distances, u + LEADER_M, "right")))
        return _Ahead(lanes, units, end, u, distances[near] - u, points[near])

    def _plan(self, route: list[LaneIndex], done: int) -> tuple:
        """Lanes (shape, start) and units along ``route`` up to ``HORIZON_M``, from the first lane's start;
        units are keyed by their lane's place on the whole route (``done`` lanes lie behind), since a
        route may pass the same unit twice within the horizon."""
        lanes, start = [], 0.0
        for index in route:
            if start > HORIZON_M + self.shapes[route[0]].length:
                break
            lanes.append((self.shapes[index], start))
            start += self.shapes[index].length
        first = lanes[0][0]
        units = []
        if is_street(first.index):  # in case the car is still leaving the junction behind
            units.append(_Unit((done, "exit"), first.index[0].split(">")[0], -math.inf,
                               JUNCTION_EXIT_M, None, 0.0))
        for number, (shape, begin) in enumerate(lanes):
            for resource, a, b in shape.units:
                # A junction lane the car is on was entered from the street before it.
                entry = -math.inf if number == 0 and not is_street(shape.index) else begin + a
                units.append(_Unit((done + number, a), resource, entry, begin + b,
                                   shape if is_street(shape.index) else None, begin))
        # Path points for finding leaders, as far as a leader is looked for past the first lane.
        near = [(shape, begin) for shape, begin in lanes if begin < lanes[0][0].length + LEADER_M]
        distances = np.concatenate([shape.path_u[1::2] + begin for shape, begin in near])  # 1 m apart
        points = np.concatenate([shape.path_xy[1::2] for shape, _ in near])
        return lanes, units, start, distances, points

    def _leader(self, vehicle: TrafficVehicle, ahead: _Ahead, others) -> tuple[float, _Leader] | None:
        """The nearest other mover on the car's path ahead, as (gap along the path, leader)."""
        x, y = vehicle.position
        others = [o for o in others if abs(o[0][0] - x) + abs(o[0][1] - y) < 1.5 * LEADER_M]
        if not others or not len(ahead.points):
            return None  # no one near enough to be within LEADER_M along the path
        positions = np.array([position for position, _, _ in others])
        reach = (vehicle.WIDTH + np.array([width for _, _, width in others])) / 2 + LEADER_SIDE_MARGIN_M
        gaps = ahead.points[None, :, :] - positions[:, None, :]
        distances2 = np.einsum("ijk,ijk->ij", gaps, gaps)
        on_path = (distances2 < (reach * reach)[:, None]).any(axis=1)
        if not on_path.any():
            return None
        first = np.where(distances2 < (reach * reach)[:, None], ahead.distances[None, :], np.inf).min(axis=1)
        mover = int(np.argmin(first))
        return float(first[mover]), _Leader(np.asarray(others[mover][1], dtype=np.float64))

    # --- giving way ------------------------------------------------------------------------

    def _way(self, vehicle: TrafficVehicle, ahead: _Ahead, leader) -> float | None:
        """Keeps the car's reservations; the path distance to stop at, if it must wait.

        The car is committed to the units it is in, those it has reserved and those too close
        after either to wait before; the next unit after a gap starts the next decision.
        """
        u, room = ahead.u, vehicle.wait_room
        units = [unit for unit in ahead.units if unit.exit - u > -HALF_LENGTH]  # the rear not yet past
        last_exit, stop, decided = -math.inf, None, False  # of the units the car is committed to
        for number, unit in enumerate(units):
            entry = unit.entry - u
            if unit.key in vehicle.committed or entry < HALF_LENGTH or entry - last_exit < room:
                if unit.key not in vehicle.committed:  # started in it, or it is too close to wait before
                    self._reserve(vehicle, [ahead.shifted(unit)], leader)
                last_exit = unit.exit - u
                continue
            if entry - HALF_LENGTH <= DECIDE_M:
                chain = [ahead.shifted(unit)]
                for later in units[number + 1:]:
                    if later.entry - u - chain[-1].exit >= room:
                        break
                    chain.append(ahead.shifted(later))
                stop = self._decide(vehicle, chain, leader, ahead.end - u)
                decided = True
            break
        if not decided:
            vehicle.waiting = None
        self._keep(vehicle, units)
        # Inside its units the car keeps the pace it promised; it brakes for the next ones once out.
        return None if last_exit > -HALF_LENGTH else stop

    def _keep(self, vehicle: TrafficVehicle, units: list[_Unit]) -> None:
        """Drops the reservations of units left behind (or off the path now)."""
        ahead = {unit.key for unit in units}
        if vehicle.committed <= ahead:
            return
        vehicle.committed &= ahead
        resources = {unit.resource for unit in units if unit.key in vehicle.committed}
        for resource in [r for r, cars in self.reservations.items() if vehicle in cars and r not in resources]:
            del self.reservations[resource][vehicle]

    def _decide(self, vehicle: TrafficVehicle, chain: list[_Unit], leader, path_end: float) -> float | None:
        """None if the car may go through ``chain`` (reserving it once close); else where to stop."""
        stop = chain[0].entry - HALF_LENGTH - STOP_GAP_M
        close = chain[0].entry - HALF_LENGTH < LOCK_M  # close enough to take it: others must see it in time
        answer = vehicle.answer
        if answer is not None and answer[0] == chain[0].key and self.time - answer[1] < RECHECK_S \
                and not (close and answer[2]):
            return None if answer[2] else stop
        bounds = vehicle.bounds(None if leader is None else float(leader[1].velocity @ vehicle.direction))
        clear = self._clear(vehicle, chain, leader, bounds, path_end)
        vehicle.answer = (chain[0].key, self.time, clear)
        if not clear:
            self._maybe_reroute(vehicle, chain[0])
            return stop
        vehicle.blocked = None
        if close:
            self._reserve(vehicle, chain, leader, bounds)
        return None

    def _reserve(self, vehicle: TrafficVehicle, units: list[_Unit], leader, bounds: _Bounds | None = None) -> None:
        if bounds is None:
            bounds = vehicle.bounds(None if leader is None else float(leader[1].velocity @ vehicle.direction))
        for unit in units:
            _widen(self.reservations.setdefault(unit.resource, {}), vehicle, self._window(unit, bounds))
            vehicle.committed.add(unit.key)

    def _maybe_reroute(self, vehicle: TrafficVehicle, first: _Unit) -> None:
        """Another way from the blocked one's first lane, if this one is too long to check or has
        kept the car waiting ``REROUTE_S``."""
        if vehicle.blocked is None or vehicle.blocked[0] != first.key:
            vehicle.blocked = (first.key, self.time)
        if vehicle.waiting == "unending" or self.time - vehicle.blocked[1] > REROUTE_S:
            place = first.key[0] - vehicle.lanes_done  # of the way's first lane on the route
            vehicle.redraw_route(place if first.shape is None else place + 1)
            vehicle.blocked = None

    def _window(self, unit: _Unit, bounds: _Bounds) -> Interval:
        """When the car can be in the unit at the earliest, and when it is surely out (sim time)."""
        beyond = HALF_LENGTH + (CLEAR_M if unit.shape is None else 0.0)
        return (self.time + bounds.first_time(unit.entry - HALF_LENGTH, high=True),
                self.time + bounds.first_time(unit.exit + beyond, high=False))

    def _clear(self, vehicle: TrafficVehicle, chain: list[_Unit], leader, bounds: _Bounds,
               path_end: float) -> bool:
        """Whether the chain is free of other traffic and of the ego car; else ``vehicle.waiting`` says why."""
        vehicle.waiting = "room"
        if leader is not None and leader[0] < chain[-1].exit + HALF_LENGTH + vehicle.DISTANCE_WANTED + 1.0:
            return False  # it would wait inside behind its leader
        windows = [self._window(unit, bounds) for unit in chain]
        if chain[-1].exit + vehicle.wait_room > path_end or not math.isfinite(windows[-1][1]):
            vehicle.waiting = "unending"  # its end lies beyond what can be checked
            return False
        for unit, (start, end) in zip(chain, windows):
            vehicle.waiting = unit.resource
            for other, (other_start, other_end) in self.reservations.get(unit.resource, {}).items():
                if other is not vehicle and other_start < end + TIME_MARGIN_S and other_end > start - TIME_MARGIN_S:
                    vehicle.waiting = "traffic"
                    return False
            if not (self._street_clear(unit, bounds) if unit.shape is not None
                    else self._junction_clear(unit, bounds)):
                return False
        vehicle.waiting = None
        return True

    def _junction_clear(self, unit: _Unit, bounds: _Bounds) -> bool:
        """No ego car in the junction area from the car's earliest arrival to its latest departure."""
        arrive = bounds.first_time(unit.entry - HALF_LENGTH, high=True)
        leave = bounds.first_time(unit.exit + HALF_LENGTH + CLEAR_M, high=False)
        for start, end in self.forecast.junction_intervals(unit.resource, self.arms[unit.resource]):
            if start < leave + TIME_MARGIN_S and end > arrive - TIME_MARGIN_S:
                return False
        return True

    def _street_clear(self, unit: _Unit, bounds: _Bounds) -> bool:
        """No ego car beside the traffic car while its body may be on one of the unit's stretches."""
        shape = unit.shape
        first, last = unit.entry - unit.begin, unit.exit - unit.begin
        stretches = [s for s in shape.stretches if s[1] >= first and s[0] <= last]
        if not stretches:
            return True
        # Times from the earliest arrival at the first stretch to the latest departure from the last.
        begin = int(np.searchsorted(bounds.high, unit.begin + stretches[0][0] - HALF_LENGTH))
        end = int(np.searchsorted(bounds.low, unit.begin + stretches[-1][1] + HALF_LENGTH, "right")) + 1
        times, low, high = TIMES[begin:end], bounds.low[begin:end], bounds.high[begin:end]
        on_stretch = np.zeros(len(times), dtype=bool)
        for a, b in stretches:
            on_stretch |= (low - HALF_LENGTH <= unit.begin + b) & (high + HALF_LENGTH >= unit.begin + a)
        speed = self.forecast.speed
        reach = layout.CAR_LENGTH_M + BESIDE_MARGIN_M + speed * TIME_MARGIN_S
        for start, u, direction in self.forecast.street_tracks(shape.index, shape.length):
            if times.size == 0 or start > times[-1] + TIME_MARGIN_S:
                continue  # the ego car cannot be on this street before the car has left it
            ego = unit.begin + u + direction * speed * (times - start)
            on_street = (times >= start) & (ego >= unit.begin - layout.CAR_LENGTH_M) \
                & (ego <= unit.begin + shape.length + layout.CAR_LENGTH_M)
            beside = (ego >= low - reach) & (ego <= high + reach)
            if np.any(on_stretch & on_street & beside):
                return False
        return True


def _has_room(shape: LaneShape, room: float) -> bool:
    """Whether a street lane has a gap of ``room`` between its junction ends and its shared stretches."""
    ends = [(-math.inf, JUNCTION_EXIT_M), *shape.shared, (shape.length - JUNCTION_ENTRY_M, math.inf)]
    return any(b[0] - a[1] >= room for a, b in zip(ends, ends[1:]))


def _widen(windows: dict, key, window: Interval) -> None:
    if key in windows:
        window = (min(windows[key][0], window[0]), max(windows[key][1], window[1]))
    windows[key] = window
