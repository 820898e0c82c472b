"""The ego car: a highway-env ``Vehicle`` whose lane is kept current cheaply.

highway-env's ``Vehicle.step`` is the motion model (its kinematic bicycle,
forward Euler at the simulation frequency, heading rate
``speed * sin(beta) / (LENGTH / 2)``). After each step it refreshes
``lane_index`` with ``RoadNetwork.get_closest_lane_index``, a Python loop over
all 90 lanes that costs more than our whole step budget; this subclass answers
the same question from ``LaneLocator``'s vectorised search, so ``lane_index``,
``lane``, position, heading and speed are at every step the ones the simulator
uses, and highway-env's observations read them. Within one decision the
simulation frames move the car several times; the lane is looked up once,
after the last of them (``refresh_lane``), which is when anyone reads it.

It also answers the two questions highway-env's ``TimeToCollision``
observation asks of a speed-controlled ``MDPVehicle``: its choice of target
speeds (just one, the speed it holds) and the index of the current one.
"""

from __future__ import annotations

import numpy as np
from highway_env.vehicle.kinematics import Vehicle

from actor.sim import layout
from actor.sim.road import LaneLocator, LanePlace


class EgoVehicle(Vehicle):
    LENGTH = layout.CAR_LENGTH_M
    WIDTH = layout.CAR_WIDTH_M
    MAX_SPEED = 40.0

    locator: LaneLocator | None = None
    place: LanePlace | None = None
    route = None  # no planned route: highway-env's TimeToCollision asks

    @property
    def target_speeds(self) -> np.ndarray:
        return np.array([self.speed])

    speed_index = 0

    def index_to_speed(self, index: int) -> float:
        return float(self.target_speeds[index])

    def on_state_update(self) -> None:
        """Called by ``Vehicle.step`` after every simulation frame: the lane waits for the last."""

    def refresh_lane(self) -> None:
        if self.locator is None:
            return
        previous = self.place.index if self.place is not None else None
        self.place = self.locator.locate(float(self.position[0]), float(self.position[1]),
                                         float(self.heading), previous)
        self.lane_index = self.place.index
        self.lane = self.road.network.get_lane(self.lane_index)
