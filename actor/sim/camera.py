"""The top-down camera: an ego-centred, heading-up colour view of the map around the car.

Not the paper's camera (that is ``front_camera.py``, the default): this one
looks straight down, so one frame shows the car's exact offset from the
centre-line, its heading and every obstacle in its window, ``topdown_ahead_m``
ahead of the car's centre to ``topdown_behind_m`` behind it and
``topdown_width_m`` across. The task is then close to fully observed; it stays
as ``env.camera = "topdown"`` for comparison. Its window is already 200 x 66.

A frame costs one ``cv2.warpAffine`` (bilinear) of the pre-drawn world
(``world_image.py``) straight into the 200 x 66 output: the crop, the rotation
and the resize of the paper's pipeline are all affine, so one warp does them
together. The ego car is then painted as a fixed rectangle, since it always sits at
the same place of a heading-up view, and traffic vehicles as rectangles
mapped through the inverse of the same warp.
(Warping into a taller image and averaging rows would alias thin kerbs a
little less at about twice the cost; at 0.5 m per output row the kerb and
pavement bands stay visible without it.)
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from actor.sim import layout
from actor.sim.geometry import rectangle_corners
from actor.sim.world_image import EGO_CAR, GRASS, TRAFFIC_CAR, WorldImage

FRAME_HEIGHT = 66
FRAME_WIDTH = 200
FRAME_SHAPE = (FRAME_HEIGHT, FRAME_WIDTH, 3)


class TopDownCamera:
    def __init__(self, world: WorldImage, ahead_m: float, behind_m: float, width_m: float) -> None:
        self.world = world
        self.ahead_m, self.behind_m, self.width_m = ahead_m, behind_m, width_m
        self.ego_rows, self.ego_columns = self.ego_pixels(FRAME_WIDTH, FRAME_HEIGHT)

    def frame(self, x: float, y: float, heading: float, movers: np.ndarray | None = None) -> np.ndarray:
        """The observation at a pose: uint8 RGB, shape (66, 200, 3), a new array each call.

        ``movers``: traffic vehicles as rows (x, y, heading, length, width)."""
        return self.view(x, y, heading, FRAME_WIDTH, FRAME_HEIGHT, movers)

    def view(self, x: float, y: float, heading: float, columns: int, rows: int,
             movers: np.ndarray | None = None) -> np.ndarray:
        """The camera window at a pose as ``rows`` x ``columns`` RGB pixels, ego car included."""
        matrix = self.matrix(x, y, heading, columns, rows)
        warped = cv2.warpAffine(self.world.pixels, matrix, (columns, rows),
                                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=(*GRASS, 0))
        frame = cv2.cvtColor(warped, cv2.COLOR_RGBA2RGB)
        if movers is not None and len(movers):
            self._draw_movers(frame, matrix, movers)
        if (columns, rows) == (FRAME_WIDTH, FRAME_HEIGHT):
            frame[self.ego_rows, self.ego_columns] = EGO_CAR
        else:
            ego_rows, ego_columns = self.ego_pixels(columns, rows)
            frame[ego_rows, ego_columns] = EGO_CAR
        return frame

    def _draw_movers(self, frame: np.ndarray, matrix: np.ndarray, movers: np.ndarray) -> None:
        """Traffic rectangles: world corners to world-image pixels, then back through the warp."""
        to_output = cv2.invertAffineTransform(matrix)
        for corners in rectangle_corners(movers):
            image_points = self.world.to_pixels(corners)
            output = image_points @ to_output[:, :2].T + to_output[:, 2]
            cv2.fillConvexPoly(frame, np.round(output * 16).astype(np.int32), TRAFFIC_CAR,
                               cv2.LINE_8, 4)

    def matrix(self, x: float, y: float, heading: float, columns: int, rows: int) -> np.ndarray:
        """The 2 x 3 affine map from output pixel (u, v) to world-image pixel (column, row).

        Output column u looks at lateral offset ``(u + 0.5) * width / columns - width / 2``
        (to the right of the car) and row v at ``ahead - (v + 0.5) * (ahead + behind) / rows``
        along the heading; the world image then maps metres to its own pixels.
        """
        scale = self.world.scale
        metres_per_column = self.width_m / columns
        metres_per_row = (self.ahead_m + self.behind_m) / rows
        forward = (math.cos(heading), math.sin(heading))
        right = (-math.sin(heading), math.cos(heading))
        along_0 = self.ahead_m - 0.5 * metres_per_row  # at v = 0
        across_0 = 0.5 * metres_per_column - self.width_m / 2  # at u = 0
        origin = (self.world.x_min, self.world.y_min)
        matrix = np.empty((2, 3))
        for axis in range(2):
            matrix[axis, 0] = scale * right[axis] * metres_per_column
            matrix[axis, 1] = -scale * forward[axis] * metres_per_row
            matrix[axis, 2] = scale * ((x, y)[axis] - origin[axis] + forward[axis] * along_0
                                       + right[axis] * across_0) - 0.5
        return matrix

    def ego_pixels(self, columns: int, rows: int) -> tuple[slice, slice]:
        """Rows and columns of the pixels whose centres lie on the ego car.

        Heading-up, the car is an axis-aligned rectangle at a fixed place of
        the frame: along in [-L/2, L/2], across in [-W/2, W/2].
        """
        metres_per_column = self.width_m / columns
        metres_per_row = (self.ahead_m + self.behind_m) / rows
        half_l, half_w = layout.CAR_LENGTH_M / 2, layout.CAR_WIDTH_M / 2
        # Pixel u's centre is (u + 0.5) * metres_per_column - width / 2 across.
        first_column = math.ceil((self.width_m / 2 - half_w) / metres_per_column - 0.5)
        last_column = math.floor((self.width_m / 2 + half_w) / metres_per_column - 0.5)
        # Pixel v's centre is ahead - (v + 0.5) * metres_per_row along.
        first_row = math.ceil((self.ahead_m - half_l) / metres_per_row - 0.5)
        last_row = math.floor((self.ahead_m + half_l) / metres_per_row - 0.5)
        return (slice(max(first_row, 0), max(last_row + 1, 0)),
                slice(max(first_column, 0), max(last_column + 1, 0)))
