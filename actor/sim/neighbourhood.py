"""The neighbourhood's geometry, derived once from the data in ``layout.py``.

Centre-lines are the streets' straight segments plus, at every junction, a
quarter circle joining each pair of perpendicular streets (drawn as short
chords), so the reward's reference also covers the ways round a corner.
Trees line the pavements and houses fill the blocks by fixed rules; nothing
here is random.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from actor.sim import layout
from actor.sim.geometry import Obstacles, Segments, arc_points, right_of

ARC_PIECES = 12  # chords per quarter circle: 2.6 cm from the true arc at 12 m radius
TREE_OFFSET_M = 7.5  # tree centres from the centre-line, beyond the pavement
TREE_SPACING_M = 12.0
TREE_RADII_M = (1.6, 2.1, 1.8)
TREE_CLEARANCE_M = 5.0  # a tree's canopy keeps this far from every centre-line
HOUSE_SETBACK_M = 14.0  # from the centre-lines around a block
HOUSE_GAP_M = 4.0
STREET_SEPARATOR = "-"  # joins a street's junctions into its name ("A1-B1"); no junction's name holds it


class LayoutError(ValueError):
    """The layout data describe an impossible neighbourhood."""


@dataclass(frozen=True)
class Pose:
    x: float
    y: float
    heading: float


@dataclass(frozen=True)
class Street:
    first: str
    second: str
    start: np.ndarray
    end: np.ndarray

    @property
    def length(self) -> float:
        return float(np.linalg.norm(self.end - self.start))

    @property
    def direction(self) -> np.ndarray:
        return (self.end - self.start) / self.length

    @property
    def heading(self) -> float:
        return math.atan2(self.direction[1], self.direction[0])

    @property
    def right(self) -> np.ndarray:
        """Unit vector to the right of the first-to-second direction."""
        return np.array(right_of(self.heading))

    def point(self, s: float, offset: float = 0.0) -> np.ndarray:
        """World point ``s`` metres along the street and ``offset`` metres to its right."""
        return self.start + s * self.direction + offset * self.right


@dataclass(frozen=True)
class Turn:
    """The centre-line curve at ``junction`` from the street towards ``first`` to the one towards ``second``."""
    junction: str
    first: str
    second: str
    centre: np.ndarray
    points: np.ndarray


@dataclass(frozen=True)
class ParkedCar:
    street: Street
    s: float
    offset: float
    yaw: float  # radians, relative to the street's first-to-second heading

    @property
    def rectangle(self) -> tuple[float, float, float, float, float]:
        x, y = self.street.point(self.s, self.offset)
        return (float(x), float(y), self.street.heading + self.yaw, layout.CAR_LENGTH_M, layout.CAR_WIDTH_M)


@dataclass(frozen=True)
class Neighbourhood:
    junctions: dict[str, np.ndarray]
    streets: tuple[Street, ...]
    neighbours: dict[str, tuple[str, ...]]
    turns: tuple[Turn, ...]
    parked_cars: tuple[ParkedCar, ...]
    trees: np.ndarray  # rows (x, y, radius)
    houses: np.ndarray  # rows (x, y, heading, length, width)
    start_poses: dict[str, tuple[Pose, ...]]
    centre_lines: Segments
    centre_line_places: tuple[str, ...]  # per centre-line segment: its street ("A1-B1") or junction
    obstacles: Obstacles

    def street(self, first: str, second: str) -> Street:
        return oriented_street(self.streets, first, second)

    def turn(self, junction: str, first: str, second: str) -> Turn | None:
        """The curve at ``junction`` from the street to ``first`` into the street to ``second``, if any."""
        for turn in self.turns:
            if (turn.junction, turn.first, turn.second) == (junction, first, second):
                return turn
            if (turn.junction, turn.second, turn.first) == (junction, first, second):
                return Turn(junction, first, second, turn.centre, turn.points[::-1])
        return None

    def bounds(self, margin: float) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of the junctions widened by ``margin`` metres."""
        points = np.array(list(self.junctions.values()))
        (x_min, y_min), (x_max, y_max) = points.min(axis=0), points.max(axis=0)
        return x_min - margin, y_min - margin, x_max + margin, y_max + margin


@functools.cache
def neighbourhood() -> Neighbourhood:
    """The one neighbourhood of the simulator (built once per process)."""
    named = [name for name in layout.JUNCTIONS if STREET_SEPARATOR in name]
    if named:
        raise LayoutError(f"junction names {named} hold {STREET_SEPARATOR!r}, which marks a street's name")
    junctions = {name: np.array(xy, dtype=np.float64) for name, xy in layout.JUNCTIONS.items()}
    streets = tuple(Street(a, b, junctions[a], junctions[b]) for a, b in layout.STREETS)
    neighbours = _neighbours(junctions, streets)
    turns = tuple(_turns(junctions, neighbours))
    centre_lines = _centre_lines(streets, turns)
    parked = tuple(_parked_car(streets, entry) for entry in layout.PARKED_CARS)
    trees = _trees(streets, centre_lines)
    houses = _houses(junctions)
    obstacles = Obstacles(
        rectangles=np.array([car.rectangle for car in parked] + [tuple(h) for h in houses]),
        circles=trees,
    )
    starts = {name: tuple(_start_pose(streets, first, second, s) for first, second, s in poses)
              for name, poses in layout.START_POSES.items()}
    places = tuple(street_name(st.first, st.second) for st in streets) + tuple(
        turn.junction for turn in turns for _ in turn.points[1:])
    return Neighbourhood(junctions, streets, neighbours, turns, parked, trees, houses, starts,
                         centre_lines, places, obstacles)


def street_name(first: str, second: str) -> str:
    """A street's name, the same for both directions: its junctions in sorted order."""
    return STREET_SEPARATOR.join(sorted((first, second)))


# --- the places an episode visits ---------------------------------------------------------------------

def is_street(place: str) -> bool:
    """A place name of ``centre_line_places`` is a street's ("B2-C2") or a junction's ("C2")."""
    return STREET_SEPARATOR in place


def place_counts(places) -> tuple[int, int]:
    """(distinct streets, distinct junctions) among place names."""
    distinct = set(places)
    streets = sum(1 for place in distinct if is_street(place))
    return streets, len(distinct) - streets


def crossed_junction(before: str, after: str) -> str | None:
    """The junction a car crossed when its place changed from street ``before`` to another street
    ``after`` with no corner curve between (straight over a junction, or a corner cut): the one
    junction both streets end at; None unless both are streets that share one."""
    if before == after or not (is_street(before) and is_street(after)):
        return None
    shared = set(before.split(STREET_SEPARATOR)) & set(after.split(STREET_SEPARATOR))
    return shared.pop() if len(shared) == 1 else None


def places_reached(hood: Neighbourhood, segment: int, along: float, reach_m: float, before: str | None = None
                   ) -> tuple[str, ...]:
    """The places a car visits at a step that leaves it nearest to centre-line ``segment``, ``along``
    (0 to 1) of the way along it, coming from place ``before`` (None at the start).

    A place counts when the car is on it more than ``reach_m`` (the most it can be off its line)
    from both its ends: near an end the car may be nearest to a place it does not drive on, as to
    the end of the cross street while it crosses a junction off the centre-line, or to the end of a
    corner curve on the street it leaves or starts from. A junction counts when its corner curve
    does, and when the car crosses it from street to street (straight on, or a corner cut short).
    """
    place = hood.centre_line_places[segment]
    metres, length = _place_extent(hood, segment, along)
    reached = [place] if reach_m < metres < length - reach_m else []
    crossed = None if before is None else crossed_junction(before, place)
    if crossed is not None:
        reached.append(crossed)
    return tuple(reached)


def _place_extent(hood: Neighbourhood, segment: int, along: float) -> tuple[float, float]:
    """(metres from the start of the place of centre-line ``segment``, the place's length): a street is
    one segment, a corner curve ARC_PIECES equal chords in a row (centre-lines: streets, then curves)."""
    chord = float(np.linalg.norm(hood.centre_lines.deltas[segment]))
    if segment < len(hood.streets):
        return along * chord, chord
    piece = (segment - len(hood.streets)) % ARC_PIECES
    return (piece + along) * chord, ARC_PIECES * chord


def oriented_street(streets, first: str, second: str) -> Street:
    """The street between two junctions, oriented from ``first`` to ``second``."""
    for street in streets:
        if (street.first, street.second) == (first, second):
            return street
        if (street.second, street.first) == (first, second):
            return Street(first, second, street.end, street.start)
    raise LayoutError(f"no street between {first} and {second}")


def _neighbours(junctions, streets) -> dict[str, tuple[str, ...]]:
    neighbours: dict[str, list[str]] = {name: [] for name in junctions}
    for street in streets:
        if street.length <= 2 * layout.TURN_RADIUS_M:
            raise LayoutError(f"street {street.first}-{street.second} is too short for its corners")
        neighbours[street.first].append(street.second)
        neighbours[street.second].append(street.first)
    dead_ends = [name for name, near in neighbours.items() if len(near) < 2]
    if dead_ends:
        raise LayoutError(f"dead ends at {', '.join(dead_ends)}")
    return {name: tuple(near) for name, near in neighbours.items()}


def _turns(junctions, neighbours):
    for name, near in neighbours.items():
        corner = junctions[name]
        for i, first in enumerate(near):
            for second in near[i + 1:]:
                away_1 = _direction(corner, junctions[first])
                away_2 = _direction(corner, junctions[second])
                if abs(float(away_1 @ away_2)) < 1e-9:
                    radius = layout.TURN_RADIUS_M
                    points = arc_points(corner, away_1, away_2, radius, ARC_PIECES)
                    yield Turn(name, first, second, corner + radius * (away_1 + away_2), points)


def _direction(start: np.ndarray, end: np.ndarray) -> np.ndarray:
    return (end - start) / np.linalg.norm(end - start)


def _centre_lines(streets, turns) -> Segments:
    starts = [street.start for street in streets] + [p for t in turns for p in t.points[:-1]]
    ends = [street.end for street in streets] + [p for t in turns for p in t.points[1:]]
    return Segments(np.array(starts), np.array(ends))


def _parked_car(streets, entry) -> ParkedCar:
    (first, second), s, offset, yaw_deg = entry
    street = oriented_street(streets, first, second)
    if not 0 < s < street.length:
        raise LayoutError(f"parked car at {s} m lies outside street {first}-{second}")
    return ParkedCar(street, s, offset, math.radians(yaw_deg))


def _trees(streets, centre_lines: Segments) -> np.ndarray:
    trees = []
    for street in streets:
        s = layout.TURN_RADIUS_M + 2.0
        while s <= street.length - layout.TURN_RADIUS_M - 2.0:
            for side in (-1.0, 1.0):
                radius = TREE_RADII_M[len(trees) % len(TREE_RADII_M)]
                x, y = street.point(s, side * TREE_OFFSET_M)
                if centre_lines.distance(x, y) - radius >= TREE_CLEARANCE_M:
                    trees.append((x, y, radius))
            s += TREE_SPACING_M
    return np.array(trees)


def _houses(junctions) -> np.ndarray:
    """Four houses per grid cell, set back from the streets around it."""
    xs = sorted({float(p[0]) for p in junctions.values()})
    ys = sorted({float(p[1]) for p in junctions.values()})
    houses = []
    for x0, x1 in zip(xs, xs[1:]):
        for y0, y1 in zip(ys, ys[1:]):
            left, right = x0 + HOUSE_SETBACK_M, x1 - HOUSE_SETBACK_M
            top, bottom = y0 + HOUSE_SETBACK_M, y1 - HOUSE_SETBACK_M
            length = (right - left - HOUSE_GAP_M) / 2
            width = (bottom - top - HOUSE_GAP_M) / 2
            for cx in (left + length / 2, right - length / 2):
                for cy in (top + width / 2, bottom - width / 2):
                    houses.append((cx, cy, 0.0, length, width))
    return np.array(houses)


def _start_pose(streets, first: str, second: str, s: float) -> Pose:
    street = oriented_street(streets, first, second)
    if not 0 < s < street.length:
        raise LayoutError(f"start pose at {s} m lies outside street {first}-{second}")
    x, y = street.point(s)
    return Pose(float(x), float(y), street.heading)
