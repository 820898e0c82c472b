"""What a car touched when it collided, named for a reader: a parked car by its street, its place along it and
how far it reaches into the road, or a house, a tree, a traffic car. Named once per collision, not per step:
the step's own test (geometry.Obstacles over everything at once) only says whether."""

from __future__ import annotations

import numpy as np

from actor.sim import layout
from actor.sim.geometry import NO_CIRCLES, NO_RECTANGLES, Obstacles
from actor.sim.neighbourhood import Neighbourhood, ParkedCar


def parked_car_name(car: ParkedCar) -> str:
    side = "right" if car.offset > 0 else "left"
    return (f"parked car on {car.street.first}-{car.street.second} {car.s:g} m from {car.street.first}, "
            f"{abs(car.offset):g} m {side} of the centre-line")


def touched(hood: Neighbourhood, pose: tuple[float, float, float], traffic: np.ndarray | None = None) -> str:
    """The first thing a car at `pose` touches: a parked car (by name), a house, a tree or a traffic car; ""
    when it touches nothing."""
    x, y, heading = pose

    def hits(rectangles, circles=NO_CIRCLES) -> bool:
        return Obstacles(rectangles, circles).hits(x, y, heading, layout.CAR_LENGTH_M, layout.CAR_WIDTH_M)

    for car in hood.parked_cars:
        if hits(np.array([car.rectangle])):
            return parked_car_name(car)
    if hits(hood.houses):
        return "a house"
    if hits(NO_RECTANGLES, hood.trees):
        return "a tree"
    if traffic is not None and len(traffic) and hits(traffic):
        return "a traffic car"
    return ""
