"""The neighbourhood as a highway-env ``Road``: a connected two-way lane graph plus obstacles.

Every street is drivable both ways and every junction joins every pair of
its streets, so each lane has a successor and highway-env's routing
(``RoadNetwork.next_lane``, ``shortest_path``) and its vehicles work on it.

Nodes are named for a junction and a neighbour of it: ``"B2>C2"`` is where the
street from B2 towards C2 leaves the junction area of B2, ``"C2<B2"`` where it
enters the junction area of C2, both ``TURN_RADIUS_M`` from their junction:

* a street lane ``("B2>C2", "C2<B2", 0)`` runs between the two, on the right
  of the centre-line (``lane_offset`` to the right of the direction of travel);
* at a junction, ``("C2<B2", "C2>X", 0)`` leads from the arriving lane into
  every other street of C2: straight across, or a quarter circle round the
  corner (radius ``TURN_RADIUS_M`` minus the offset for a right turn, plus it
  for a left turn).

The simulator's own per-step queries (where is the car, which lane is it on)
are answered by ``LaneLocator`` from points sampled along these same lanes,
in one vectorised pass instead of highway-env's Python loop over lanes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import numba
import numpy as np
from highway_env.road.lane import AbstractLane, CircularLane, LineType, StraightLane
from highway_env.road.road import LaneIndex, Road, RoadNetwork
from highway_env.vehicle.objects import Obstacle

from actor.sim import layout
from actor.sim.neighbourhood import Neighbourhood

SAMPLE_SPACING_M = 0.5  # between the lane points LaneLocator searches
TIE_M = 0.3  # a lane this much worse than the best still counts as the best (continuity)
CELL_M = 5.0  # LaneLocator's grid: a car's cell and its 8 neighbours hold every lane point within 5 m
SPEED_LIMIT = 14.0  # m/s, what highway-env's vehicles aim for at most


def leaving(junction: str, towards: str) -> str:
    return f"{junction}>{towards}"


def arriving(junction: str, coming_from: str) -> str:
    return f"{junction}<{coming_from}"


def road_network(hood: Neighbourhood, lane_offset: float, lane_width: float) -> RoadNetwork:
    network = RoadNetwork()
    for junction, neighbours in hood.neighbours.items():
        for towards in neighbours:
            network.add_lane(leaving(junction, towards), arriving(towards, junction),
                             _street_lane(hood, junction, towards, lane_offset, lane_width))
        for coming_from in neighbours:
            for towards in neighbours:
                if towards != coming_from:
                    network.add_lane(arriving(junction, coming_from), leaving(junction, towards),
                                     _junction_lane(hood, junction, coming_from, towards,
                                                    lane_offset, lane_width))
    return network


def _stub(hood: Neighbourhood, junction: str, towards: str) -> tuple[np.ndarray, np.ndarray]:
    """Where the street towards ``towards`` leaves the junction area, and its direction."""
    corner = hood.junctions[junction]
    direction = hood.junctions[towards] - corner
    direction = direction / np.linalg.norm(direction)
    return corner + layout.TURN_RADIUS_M * direction, direction


def _right(direction: np.ndarray) -> np.ndarray:
    return np.array([-direction[1], direction[0]])


def _street_lane(hood, junction, towards, offset, width) -> StraightLane:
    start, direction = _stub(hood, junction, towards)
    end, _ = _stub(hood, towards, junction)
    shift = offset * _right(direction)
    return StraightLane(start + shift, end + shift, width=width,
                        line_types=(LineType.STRIPED, LineType.CONTINUOUS), speed_limit=SPEED_LIMIT)


def _junction_lane(hood, junction, coming_from, towards, offset, width) -> AbstractLane:
    entry, entry_back = _stub(hood, junction, coming_from)
    exit_, exit_direction = _stub(hood, junction, towards)
    travel_in = -entry_back  # the direction of travel arriving at the junction
    if abs(float(travel_in @ exit_direction) - 1.0) < 1e-9:  # straight across
        return StraightLane(entry + offset * _right(travel_in), exit_ + offset * _right(exit_direction),
                            width=width, line_types=(LineType.NONE, LineType.NONE),
                            speed_limit=SPEED_LIMIT)
    centre = hood.junctions[junction] + layout.TURN_RADIUS_M * (entry_back + exit_direction)
    start_phase = math.atan2(*(entry - centre)[::-1])
    end_phase = math.atan2(*(exit_ - centre)[::-1])
    sweep = (end_phase - start_phase + math.pi) % (2 * math.pi) - math.pi
    clockwise = sweep > 0  # on the y-down map: a right turn, the lane on the inside
    radius = layout.TURN_RADIUS_M - offset if clockwise else layout.TURN_RADIUS_M + offset
    return CircularLane(centre, radius, start_phase, start_phase + sweep, clockwise=clockwise,
                        width=width, line_types=(LineType.NONE, LineType.NONE), speed_limit=SPEED_LIMIT)


def neighbourhood_road(hood: Neighbourhood, lane_offset: float, lane_width: float,
                       np_random: np.random.Generator | None = None) -> Road:
    """The road with parked cars, trees and houses as highway-env ``Obstacle`` objects."""
    road = Road(network=road_network(hood, lane_offset, lane_width), np_random=np_random)
    for box, lane_index in zip(obstacle_boxes(hood), obstacle_lanes(hood, road.network, lane_offset, lane_width)):
        road.objects.append(_obstacle(road, *box, lane_index))
    return road


def obstacle_boxes(hood: Neighbourhood) -> list[tuple[float, float, float, float, float]]:
    """(x, y, heading, length, width) of every parked car, house and tree (a tree as its bounding square)."""
    rectangles = [car.rectangle for car in hood.parked_cars] + [tuple(h) for h in hood.houses]
    return rectangles + [(x, y, 0.0, 2 * r, 2 * r) for x, y, r in hood.trees]


# (what, id(hood), lane offset, lane width) -> (the hood, what was built of that road)
_OF_ROAD: dict[tuple[str, int, float, float], tuple[Neighbourhood, Any]] = {}


def once_per_road(what: str, hood: Neighbourhood, lane_offset: float, lane_width: float, build: Callable[[], Any]):
    """What build() makes of one road (the hood and its lanes' geometry), made once per process and shared
    by its simulators, read only: every simulator of a process drives the same road, and building its
    lookups was most of building a simulator (about 0.9 s), which an evaluation worker of many
    simulators paid for each."""
    key = (what, id(hood), lane_offset, lane_width)
    cached = _OF_ROAD.get(key)
    if cached is None or cached[0] is not hood:  # the hood held too, so that a reused id cannot match
        cached = _OF_ROAD[key] = (hood, build())
    return cached[1]


def obstacle_lanes(hood: Neighbourhood, network: RoadNetwork, lane_offset: float, lane_width: float
                   ) -> list[LaneIndex]:
    """The lane highway-env places each obstacle on (its get_closest_lane_index, a Python loop over every
    lane), once per process and road."""
    return once_per_road("obstacle lanes", hood, lane_offset, lane_width, lambda: [
        network.get_closest_lane_index(np.array([x, y], dtype=np.float64), heading)
        for x, y, heading, _, _ in obstacle_boxes(hood)])


def lane_locator(hood: Neighbourhood, network: RoadNetwork, lane_offset: float, lane_width: float) -> LaneLocator:
    """The LaneLocator of the road, once per process and road (it reads the network only when built)."""
    return once_per_road("lane locator", hood, lane_offset, lane_width, lambda: LaneLocator(network))


def _obstacle(road: Road, x: float, y: float, heading: float, length: float, width: float,
              lane_index: LaneIndex) -> Obstacle:
    obstacle = Obstacle(None, [x, y], heading=heading)  # without a road it skips its own lane lookup
    obstacle.road = road
    obstacle.LENGTH, obstacle.WIDTH = length, width
    obstacle.diagonal = math.hypot(length, width)
    obstacle.lane_index = lane_index
    obstacle.lane = road.network.get_lane(lane_index)
    return obstacle


@dataclass(frozen=True)
class LanePlace:
    index: LaneIndex
    longitudinal: float  # metres along the lane
    lateral: float  # metres to the right of the lane's centre


class LaneLocator:
    """The lane a car is on, given its position and heading, from points sampled along every lane.

    Of the lane points whose direction lies within 90 degrees of the car's
    heading, the best wins, so a car is always on a lane of its direction of
    travel; a point's score is, as in highway-env's ``distance_with_heading``,
    its distance in metres plus the angle in radians between its direction and
    the car's heading. Where lanes overlap (a junction's lanes all start where the
    arriving lane ends) several are nearest within sampling error; then the
    car's previous lane or one of its successors is kept, so the lane index
    does not flicker between equally near lanes. Otherwise the same answer as
    highway-env's ``get_closest_lane_index``, at a fraction of its cost.
    """

    def __init__(self, network: RoadNetwork) -> None:
        self.indices: list[LaneIndex] = []
        points, directions, lane_of, along = [], [], [], []
        for _from, tos in network.graph.items():
            for _to, lanes in tos.items():
                for number, lane in enumerate(lanes):
                    s = np.linspace(0.0, lane.length, max(2, int(lane.length / SAMPLE_SPACING_M) + 1))
                    points.append(np.array([lane.position(v, 0.0) for v in s]))
                    headings = np.array([lane.heading_at(v) for v in s])
                    directions.append(np.stack([np.cos(headings), np.sin(headings)], axis=1))
                    lane_of.append(np.full(len(s), len(self.indices)))
                    along.append(s)
                    self.indices.append((_from, _to, number))
        self.points = np.concatenate(points)
        self.directions = np.concatenate(directions)
        self.lane_of = np.concatenate(lane_of)
        self.along = np.concatenate(along)
        number = {index: n for n, index in enumerate(self.indices)}
        # continues[a, b]: lane b is lane a or one of its successors.
        self.continues = np.eye(len(self.indices), dtype=bool)
        for n, index in enumerate(self.indices):
            for after in network.graph.get(index[1], {}):
                self.continues[n, number[(index[1], after, 0)]] = True
        self.number = number
        self._build_grid()

    def _build_grid(self) -> None:
        """For every grid cell, the lane points of it and its eight neighbours."""
        self.origin = self.points.min(axis=0) - CELL_M
        cells = np.floor((self.points - self.origin) / CELL_M).astype(int)
        self.shape = tuple(cells.max(axis=0) + 2)
        owners: dict[tuple[int, int], list[int]] = {}
        for point, (i, j) in enumerate(cells):
            for di in (-1, 0, 1):
                for dj in (-1, 0, 1):
                    owners.setdefault((i + di, j + dj), []).append(point)
        self.near = {cell: (np.array(points), self.points[points], self.directions[points],
                            self.lane_of[points]) for cell, points in owners.items()}
        self.everything = (None, self.points, self.directions, self.lane_of)

    def locate(self, x: float, y: float, heading: float, previous: LaneIndex | None = None) -> LanePlace:
        """The car's lane, preferring ``previous`` or its successors among equally near ones.

        Far from every lane (off the map) the whole set is searched."""
        cell = (int((x - self.origin[0]) // CELL_M), int((y - self.origin[1]) // CELL_M))
        candidates = self.near.get(cell, self.everything)
        keep = None if previous is None else self.continues[self.number[previous]]
        nearest = self._nearest(x, y, heading, candidates, keep)
        if nearest is None:
            nearest = self._nearest(x, y, heading, self.everything, keep)
        gaps = self.points[nearest] - (x, y)
        # Lateral offset: the gap's component on the lane's right, (-dy, dx) of the direction.
        dx, dy = self.directions[nearest]
        gap_x, gap_y = -gaps
        lateral = -dy * gap_x + dx * gap_y
        longitudinal = self.along[nearest] + dx * gap_x + dy * gap_y
        return LanePlace(self.indices[self.lane_of[nearest]], float(longitudinal), float(lateral))

    def _nearest(self, x: float, y: float, heading: float, candidates: tuple,
                 keep: np.ndarray | None) -> int | None:
        """The best point facing ``heading`` among (indices, points, directions, lanes), or
        one of the lanes marked in ``keep`` within TIE_M of it."""
        indices, points, directions, lanes = candidates
        best = _best_point(points, directions, lanes, x, y, math.cos(heading), math.sin(heading),
                           self.continues[0] if keep is None else keep, keep is not None)
        if best < 0:
            return None
        return best if indices is None else int(indices[best])


@numba.njit(cache=True)
def _best_point(points, directions, lanes, x, y, cos_h, sin_h, keep, use_keep):
    """Index of the point of least score (distance plus the angle between its direction and
    the heading) among those facing the heading, or of the best point on a lane marked in
    ``keep`` if that scores within TIE_M of it; -1 if no point faces the heading."""
    best, best_score, kept, kept_score = -1, np.inf, -1, np.inf
    for i in range(len(points)):
        facing = directions[i, 0] * cos_h + directions[i, 1] * sin_h
        if facing <= 0.0:
            continue
        gap_x, gap_y = points[i, 0] - x, points[i, 1] - y
        score = math.sqrt(gap_x * gap_x + gap_y * gap_y) + math.acos(min(facing, 1.0))
        if score < best_score:
            best, best_score = i, score
        if use_keep and keep[lanes[i]] and score < kept_score:
            kept, kept_score = i, score
    if kept >= 0 and kept_score <= best_score + TIE_M:
        return kept
    return best
