"""Kinematic bicycle model at constant speed, integrated exactly over one step.

The state is the car's centre (x, y) and heading. With the centre midway
between the axles, the slip angle is beta = atan(tan(delta) / 2) and the
heading turns at omega = v * sin(beta) / (wheelbase / 2): the same model as
highway-env's ``Vehicle.step``. Steering is held for the whole step, so the
centre moves on a circle of radius v / omega and the closed form below is
exact for any step length: no sub-steps, no integration error.
"""

from __future__ import annotations

import math


def slip_angle(steering: float) -> float:
    return math.atan(0.5 * math.tan(steering))


def bicycle_step(x: float, y: float, heading: float, speed: float, steering: float,
                 wheelbase: float, dt: float) -> tuple[float, float, float]:
    """The pose after ``dt`` seconds at constant ``speed`` and ``steering`` (radians)."""
    beta = slip_angle(steering)
    yaw_rate = speed * math.sin(beta) / (wheelbase / 2)
    course = heading + beta  # direction of travel of the centre
    turn = yaw_rate * dt
    if abs(turn) < 1e-9:
        return x + speed * dt * math.cos(course), y + speed * dt * math.sin(course), heading
    radius = speed / yaw_rate
    x += radius * (math.sin(course + turn) - math.sin(course))
    y += radius * (math.cos(course) - math.cos(course + turn))
    return x, y, heading + turn


def turning_radius(steering: float, wheelbase: float) -> float:
    """Radius of the circle the car's centre follows at a fixed steering angle."""
    return (wheelbase / 2) / math.sin(slip_angle(steering))
