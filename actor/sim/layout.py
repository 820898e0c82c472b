"""The neighbourhood as data: junctions, streets, parked cars, start poses.

Coordinates are metres in highway-env's frame: x grows to the east, y to the
south (image rows grow with y) and headings are radians from +x towards +y. A
positive steering angle therefore turns the car clockwise on the map, that is
to the driver's right, as in highway-env.

A street is one carriageway between two junctions; its centre-line is the
straight segment between them and is the reward's reference. A lateral offset
is measured from that centre-line, positive to the right of the street's
first-to-second direction. Trees and houses follow from the grid by the fixed
rules in ``neighbourhood.py``; everything else is listed here.
"""

from __future__ import annotations

# Three rows of four junctions: 3 x 2 blocks of about 70 m.
JUNCTIONS: dict[str, tuple[float, float]] = {
    "A1": (0.0, 0.0), "B1": (75.0, 0.0), "C1": (145.0, 0.0), "D1": (215.0, 0.0),
    "A2": (0.0, 70.0), "B2": (75.0, 70.0), "C2": (145.0, 70.0), "D2": (215.0, 70.0),
    "A3": (0.0, 140.0), "B3": (75.0, 140.0), "C3": (145.0, 140.0), "D3": (215.0, 140.0),
}

# The street C2-C3 is left out, so the grid has corners (A1, D1, A3, D3), one
# X-junction (B2), T-junctions, a straight run through C3 and one long block.
STREETS: tuple[tuple[str, str], ...] = (
    ("A1", "B1"), ("B1", "C1"), ("C1", "D1"),
    ("A2", "B2"), ("B2", "C2"), ("C2", "D2"),
    ("A3", "B3"), ("B3", "C3"), ("C3", "D3"),
    ("A1", "A2"), ("A2", "A3"),
    ("B1", "B2"), ("B2", "B3"),
    ("C1", "C2"),
    ("D1", "D2"), ("D2", "D3"),
)

# Centre-line radius of the curve joining two perpendicular streets at a junction.
TURN_RADIUS_M = 12.0

CAR_LENGTH_M = 4.5
CAR_WIDTH_M = 1.8

# Lateral offsets of parked cars (car centre from the centre-line): at the kerb
# a car leaves the centre-line 0.8 m of room on each side of a passing car;
# a badly parked one reaches into the driving line and must be steered around.
KERB = 2.6
INTRUDING = 1.3  # inner edge 0.4 m from the centre-line
DEEP = 0.9  # inner edge on the centre-line

# (street, metres from the street's first junction, lateral offset, yaw in degrees)
PARKED_CARS: tuple[tuple[tuple[str, str], float, float, float], ...] = (
    (("A1", "B1"), 22.0, +KERB, 0.0),
    (("A1", "B1"), 34.0, +KERB, 0.0),
    (("A1", "B1"), 52.0, -INTRUDING, 0.0),
    (("B1", "C1"), 25.0, -KERB, 0.0),
    (("B1", "C1"), 45.0, +DEEP, 0.0),
    (("C1", "D1"), 30.0, +KERB, 0.0),
    (("C1", "D1"), 42.0, +KERB, 0.0),
    (("A2", "B2"), 20.0, -KERB, 0.0),
    (("A2", "B2"), 38.0, +INTRUDING, 0.0),
    (("B2", "C2"), 28.0, -DEEP, 0.0),
    (("B2", "C2"), 50.0, +KERB, 0.0),
    (("C2", "D2"), 35.0, -2.0, 12.0),  # parked askew, its front corner sticks out
    (("A3", "B3"), 30.0, -KERB, 0.0),
    (("A3", "B3"), 48.0, -KERB, 0.0),
    (("B3", "C3"), 40.0, +INTRUDING, 0.0),
    (("C3", "D3"), 25.0, -KERB, 0.0),
    (("C3", "D3"), 50.0, +KERB, 0.0),
    (("A1", "A2"), 35.0, +INTRUDING, 0.0),
    (("A2", "A3"), 25.0, +KERB, 0.0),
    (("B1", "B2"), 30.0, -KERB, 0.0),
    (("B1", "B2"), 48.0, +KERB, 0.0),
    (("B2", "B3"), 40.0, -INTRUDING, 0.0),
    (("C1", "C2"), 35.0, +2.0, -10.0),
    (("D1", "D2"), 28.0, -KERB, 0.0),
    (("D1", "D2"), 45.0, -DEEP, 0.0),
    (("D2", "D3"), 35.0, +KERB, 0.0),
)

# Start poses: on a street's centre-line, this many metres from the first
# junction, heading towards the second. The two sets share no pose.
START_POSES: dict[str, tuple[tuple[str, str, float], ...]] = {
    "train": (
        ("A1", "B1", 15.0), ("C1", "B1", 40.0), ("D1", "D2", 20.0), ("B2", "A2", 50.0),
        ("B1", "B2", 15.0), ("C2", "D2", 12.0), ("A3", "A2", 30.0), ("D3", "C3", 20.0),
        ("B3", "B2", 50.0), ("C3", "B3", 50.0),
    ),
    "test": (
        ("B1", "C1", 12.0), ("D1", "C1", 45.0), ("A2", "A3", 20.0), ("A2", "B2", 55.0),
        ("C2", "C1", 20.0), ("D2", "D3", 15.0), ("B3", "A3", 40.0), ("A2", "A1", 20.0),
        ("C2", "B2", 15.0), ("C3", "D3", 30.0),
    ),
}
