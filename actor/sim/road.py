"""The neighbourhood as a highway-env ``Road``: a ``RoadNetwork`` of lanes plus obstacles.

Each street is one ``StraightLane`` as wide as the carriageway (junction to
junction), each corner curve a ``CircularLane``; parked cars, trees and houses
are ``Obstacle`` objects of their own sizes. The simulator's own per-step
checks use the numpy arrays of ``neighbourhood.py``, which hold the same
geometry; this road is what highway-env's renderers (e.g. its
``GrayscaleObservation``) and tools see.
"""

from __future__ import annotations

import math

import numpy as np
from highway_env.road.lane import CircularLane, LineType, StraightLane
from highway_env.road.road import Road, RoadNetwork
from highway_env.vehicle.objects import Obstacle

from actor.sim import layout
from actor.sim.neighbourhood import Neighbourhood, Turn


def road_network(hood: Neighbourhood, road_half_width: float) -> RoadNetwork:
    network = RoadNetwork()
    edges = (LineType.CONTINUOUS, LineType.CONTINUOUS)
    for street in hood.streets:
        network.add_lane(street.first, street.second,
                         StraightLane(street.start, street.end, width=2 * road_half_width,
                                      line_types=edges, speed_limit=20))
    for turn in hood.turns:
        # A curve is its own short road between two named points beside the junction.
        network.add_lane(f"{turn.junction}>{turn.first}", f"{turn.junction}>{turn.second}",
                         _circular_lane(turn, road_half_width))
    return network


def _circular_lane(turn: Turn, road_half_width: float) -> CircularLane:
    first, last = turn.points[0] - turn.centre, turn.points[-1] - turn.centre
    start_phase = math.atan2(first[1], first[0])
    end_phase = math.atan2(last[1], last[0])
    sweep = (end_phase - start_phase + math.pi) % (2 * math.pi) - math.pi
    return CircularLane(turn.centre, layout.TURN_RADIUS_M, start_phase, start_phase + sweep,
                        clockwise=sweep > 0, width=2 * road_half_width,
                        line_types=(LineType.NONE, LineType.NONE), speed_limit=20)


def neighbourhood_road(hood: Neighbourhood, road_half_width: float,
                       np_random: np.random.Generator | None = None) -> Road:
    road = Road(network=road_network(hood, road_half_width), np_random=np_random)
    rectangles = [car.rectangle for car in hood.parked_cars] + [tuple(h) for h in hood.houses]
    squares = [(x, y, 0.0, 2 * r, 2 * r) for x, y, r in hood.trees]
    for x, y, heading, length, width in rectangles + squares:
        road.objects.append(_obstacle(road, x, y, heading, length, width))
    return road


def _obstacle(road: Road, x: float, y: float, heading: float, length: float, width: float) -> Obstacle:
    obstacle = Obstacle(road, [x, y], heading=heading)
    obstacle.LENGTH, obstacle.WIDTH = length, width
    obstacle.diagonal = math.hypot(length, width)
    return obstacle
