"""The perspective front camera: what a camera on the car's roof sees of the street ahead.

The paper films from the dashboard, then crops the image top and bottom to the
road and resizes it to 200 x 66. Here the sensor is a pinhole camera
``height_m`` above the car's centre, pitched ``pitch_deg`` down, with a 16:9
image of square pixels that is 200 wide for ``hfov_deg`` across (200 x 112,
focal length 100 px at 90 degrees). The crop keeps sensor rows 35 to 100: at
the default pitch that is from 7 degrees above the horizon (12 rows of sky:
the walls, canopies and far roofs of the street) down to 29 degrees below it,
where the ground is 2.5 m ahead of the camera, just past the bonnet. The crop
is already 200 wide, so its resize is the identity and the frame is rendered
straight at 200 x 66; other sizes (``view``) scale the focal length with the
width and keep the crop's centre. Rendering at twice the size and shrinking
with ``cv2.INTER_AREA`` smooths edges and the far dashes, but measured 1.5
times the cost of a frame; the distant ground, where aliasing is worst, fades
into haze anyway, so it is not done.

The ground is flat and the camera does not roll, so the ray through a pixel
meets the ground at a projective function of the pixel: one homography
(``cv2.warpPerspective``, bilinear) maps the frame's ground rows to the
pre-drawn ground image (``world_image.ground_image``), and the distance
ahead depends on the row alone. Only rows whose ground lies within
``range_m`` are warped; above them the frame shows haze. The far half of the
range fades into that haze row by row, and every object fades by how far
ahead its footprint starts, so nothing pops into view at the range.

Above the ground stand convex solids, parked cars and traffic as boxes and
houses as boxes under a gable roof, each face shaded once by its normal
against a fixed sun. A solid is drawn with its front faces only (back-face
culling is exact for a convex solid), and a face that crosses the near plane
is clipped to it, so a car being passed still shows the part in view. Trees
are a trunk (the silhouette of a thin round post, a quad facing the camera)
under a canopy (a sphere, drawn as a disc with a sunlit side). Objects are
painted from far to near by the distance to the nearest point of their
footprint, which orders things standing apart on a street correctly. Whatever
is behind the car, beside it outside the field of view, or hidden behind
something nearer is thus not in the frame.

The per-frame cost is in calls, not in array sizes: a frame holds a few dozen
small shapes, and through OpenCV each would be one Python call of about 4
microseconds, nearly all of it the call itself, with dozens of small numpy
operations around them for culling. So everything after the ground is one
compiled pass (numba, ``_paint``): it tests every object's bounding sphere
against the frustum and the range, sorts those in view far to near, projects
their parts and fills them. Filling follows OpenCV's conventions (fixed point
with SUBPIXEL_BITS fractional bits, pixel centres at whole pixels); a pixel is
filled when its centre lies within half a pixel of the shape in x and in y,
which keeps the fuller edges of OpenCV's 8-connected outlines, so a frame
drawn this way differs from one drawn by ``cv2.fillConvexPoly`` and
``cv2.circle`` in about 0.4% of its pixels (measured over 1,000 frames of
random driving), all along edges. The compiled functions all live in this
module because numba's cache is keyed on the source file of each function: a
change to a function in another module would not recompile the callers cached
here.

Coordinates are the simulator's: metres, x east, y south, z up, headings
from +x towards +y. The image's columns grow to the driver's right, so the
picture is not mirrored.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np

from actor.sim.camera import FRAME_HEIGHT, FRAME_WIDTH
from actor.sim.geometry import rectangle_corners
from actor.sim.neighbourhood import Neighbourhood
from actor.sim.world_image import (CANOPY, GRASS, HAZE, HOUSE_ROOF, HOUSE_WALL, PARKED_CAR, SKY,
                                   TRAFFIC_CAR, TRUNK, WorldImage)

SUBPIXEL_BITS = 4
ONE = 1 << SUBPIXEL_BITS
GROW = ONE // 2  # how far (fixed point) beyond a shape a pixel centre may lie and be filled
SENSOR_ROWS = 112  # 16:9 at FRAME_WIDTH columns
CROP_TOP_ROW = 35  # the frame is sensor rows CROP_TOP_ROW .. CROP_TOP_ROW + FRAME_HEIGHT - 1

NEAR_M = 0.1  # faces are clipped to this depth in front of the camera
EDGE_ON = 1e-9  # a face is drawn if the camera is beyond its plane by more (seen edge-on it is a line)
FOG_START = 0.5  # fraction of the range where the fade into haze begins
SKY_GRADIENT_DEG = 20.0  # elevation where the sky has turned from haze to SKY

CAR_HEIGHT_M = 1.5
TRUNK_RADIUS_M = 0.3
CANOPY_CENTRE_M = 4.0  # a canopy of radius 2 m spans 2 m to 6 m above the ground
HOUSE_WALL_HEIGHTS_M = (5.0, 6.5, 5.5)  # cycled over the houses so that the rooflines differ
ROOF_RISE_M = 3.5

# Shading: brightness = AMBIENT + DIFFUSE * max(0, normal . SUN), at most 1.
SUN = np.array([-0.35, 0.45, 0.82]) / np.linalg.norm([-0.35, 0.45, 0.82])  # towards the sun
SUN_XYZ = tuple(SUN.tolist())
AMBIENT = 0.6
DIFFUSE = 0.4
HIGHLIGHT_SHIFT = 0.35  # a canopy's sunlit disc: offset towards the sun, times the canopy's radius
HIGHLIGHT_RADIUS = 0.6  # and its radius
# Far away a part is too small to matter and not drawn: a sunlit side of radius
# below this (in frame pixels; beyond about 30 m), a trunk narrower (beyond 40 m).
HIGHLIGHT_MIN_PX = 4.0
TRUNK_MIN_PX = 1.5

HAZE_RGB = np.array(HAZE, dtype=np.float64)

# Solids are stored with FACES faces of OUTLINE vertices each: shorter outlines
# repeat their last vertex, and a padding face has a zero plane (never drawn).
FACES = 6
OUTLINE = 5
# A unit box in its own frame (along, across, up, 1): bottom corners 0-3 in
# ``rectangle_corners``' order (front right, front left, back left, back
# right), the same corners at the top 4-7; faces front, back, right, left,
# top, padding, with their outward planes.
BOX_VERTICES = np.array([(a, b, z, 1.0) for z in (0.0, 1.0) for a, b in ((1, 1), (1, -1), (-1, -1), (-1, 1))])
BOX_FACES = np.array([(0, 1, 5, 4, 4), (2, 3, 7, 6, 6), (3, 0, 4, 7, 7), (1, 2, 6, 5, 5),
                      (4, 5, 6, 7, 7), (0, 0, 0, 0, 0)])
BOX_OUTLINES = BOX_VERTICES[BOX_FACES.ravel()]
BOX_PLANES = np.array([(1, 0, 0, -1), (-1, 0, 0, -1), (0, 1, 0, -1), (0, -1, 0, -1), (0, 0, 1, -1),
                       (0, 0, 0, 0)], dtype=np.float64)
# House vertices: a box's up to the wall tops, then the ridge's front (8) and
# back (9) ends. Faces: front and back walls with their gables, right and
# left walls, right and left roof.
HOUSE_FACES = np.array([(0, 1, 5, 8, 4), (2, 3, 7, 9, 6), (3, 0, 4, 7, 7), (1, 2, 6, 5, 5),
                        (4, 8, 9, 7, 7), (5, 6, 9, 8, 8)])
# A tree is three camera-facing parts: its trunk (a quad between its foot and its
# top, widened along the camera's right axis), its canopy's disc and the disc's
# sunlit side (discs drawn as circles).
TREE_PARTS = 3

# The culling tests after the five frustum planes (``_in_view``: ahead less reach,
# the footprint's axes against the heading, the camera's offset along and across
# them) are linear in the camera's (fx, fy, x, y, fx x + fy y, 1): for each test,
# the feature column and the term that multiplies it.
CULL_TERM_NAMES = ("fx", "fy", "x", "y", "f.p", "1")
CULL_TESTS = ({0: "fx", 1: "fy", 3: "-f.p", 8: "-1"}, {4: "fx", 5: "fy"}, {4: "fy", 5: "-fx"},
              {4: "-x", 5: "-y", 6: "1"}, {4: "-y", 5: "x", 7: "1"})


def _cull_terms() -> np.ndarray:
    """CULL_TESTS as a (terms, tests x 9 features) matrix: (terms) @ it gives the tests' rows."""
    terms = np.zeros((len(CULL_TERM_NAMES), len(CULL_TESTS), 9))
    for test, columns in enumerate(CULL_TESTS):
        for column, term in columns.items():
            terms[CULL_TERM_NAMES.index(term.lstrip("-")), test, column] = -1.0 if term[0] == "-" else 1.0
    return terms.reshape(len(CULL_TERM_NAMES), -1)


CULL_TERMS = _cull_terms()


@dataclass(frozen=True)
class _Extents:
    """What culling needs of each object, one column per object, so that one matrix product
    per frame (``_in_view``) gives every test and each test's values are contiguous."""
    features: np.ndarray  # (9, n): sphere centre x, y, z, 1, cos, sin, x cos + y sin, y cos - x sin, reach
    radius: np.ndarray  # (n,) bounding sphere radius
    half: np.ndarray  # (2, n) half length and half width of the footprint rectangle (centred below
    # the sphere, turned by the heading in cos, sin), widened all round by ``reach``

    def join(self, other: _Extents) -> _Extents:
        return _Extents(np.hstack([self.features, other.features]), np.hstack([self.radius, other.radius]),
                        np.hstack([self.half, other.half]))


@dataclass(frozen=True)
class _Parts:
    """What is drawn, as arrays over parts: the faces of solids (polygons) and the parts of
    trees (a quad and two discs, all facing the camera)."""
    points: np.ndarray  # (n, OUTLINE, 5): homogeneous world points (x, y, z, 1), each with how far
    # to move it along the camera's right axis (which keeps a tree's parts facing the camera)
    planes: np.ndarray  # (n, 4): a part is drawn if plane . (camera, 1) > EDGE_ON (faces:
    # outward planes, scaled by the inverse sizes for boxes, which keeps the sign; trees: always)
    colours: np.ndarray  # (n, 3) shaded RGB
    kinds: np.ndarray  # (n, 3): whether a disc (centre at point 0, radius out to point 1); the
    # depth point 0 must exceed, else the part is not drawn (a face is clipped instead: -inf);
    # the smallest size, in frame pixels, at which the part is drawn: from point 0 to point 1
    # across the image (a disc's radius, a trunk's width)

    def take(self, index: np.ndarray) -> _Parts:
        return _Parts(self.points[index], self.planes[index], self.colours[index], self.kinds[index])

    def join(self, other: _Parts) -> _Parts:
        return _Parts(*(np.concatenate([a, b]) for a, b in ((self.points, other.points),
                                                            (self.planes, other.planes),
                                                            (self.colours, other.colours),
                                                            (self.kinds, other.kinds))))


@dataclass(frozen=True)
class _Set:
    """Objects as the compiled pass (``_paint``) takes them: C-contiguous arrays, one row per
    object for culling and one per part for drawing."""
    arrays: tuple[np.ndarray, ...]  # features (n, 9), radius (n,), half (n, 2), first (n + 1,):
    # object i's parts are rows first[i] .. first[i + 1] - 1 of the parts' points (p, OUTLINE, 5),
    # planes (p, 4), colours (p, 3) and kinds (p, 3) (see _Extents and _Parts)

    @staticmethod
    def of(extents: _Extents, parts: _Parts, counts: np.ndarray) -> _Set:
        first = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        arrays = (extents.features.T, extents.radius, extents.half.T, first, parts.points, parts.planes,
                  parts.colours, parts.kinds)
        return _Set(tuple(np.ascontiguousarray(a) for a in arrays))

    @staticmethod
    def of_movers(movers: np.ndarray) -> _Set:
        """Traffic vehicles, rows (x, y, heading, length, width): boxes CAR_HEIGHT_M tall."""
        movers = np.asarray(movers, dtype=np.float64)
        parts = _face_parts(*_box_faces(movers, CAR_HEIGHT_M, TRAFFIC_CAR))
        return _Set.of(_box_extents(movers, CAR_HEIGHT_M), parts, np.full(len(movers), FACES))


@dataclass(frozen=True)
class _Lens:
    """What depends on the output size only: intrinsics, frustum, sky, fog rows."""
    zoom: float  # columns / FRAME_WIDTH
    to_fixed: np.ndarray  # 3 x 3 intrinsics to cv2's fixed point: camera point to (u z, v z, z)
    ground_top: int  # first row whose ground lies within range; the rows from here are warped
    from_band: np.ndarray  # 3 x 3: band pixel (u, v - ground_top, 1) to camera ray (x/z, y/z, 1)
    background: np.ndarray  # (rows, columns, 4) sky and haze
    fog_ground: np.ndarray  # (fog rows, columns) float32 weight of the ground in the rows from ground_top
    fog_haze: np.ndarray  # the same rows' weight of the haze
    haze_rows: np.ndarray  # (fog rows, columns, 4) haze
    planes: np.ndarray  # (5, 4) frustum planes (a, b, c, d) in camera coordinates: p is outside
    # a plane if (a, b, c) . p + d > 0; the four frame edges, then the near plane


@dataclass(frozen=True)
class _Pose:
    position: np.ndarray  # (4,) homogeneous camera centre
    to_camera: np.ndarray  # 4 x 4: homogeneous world point to camera point (right, down, forward)
    forward: tuple[float, float]  # horizontal unit vector along the heading


class PerspectiveCamera:
    def __init__(self, world: WorldImage, hood: Neighbourhood, height_m: float = 1.4,
                 pitch_deg: float = 5.0, hfov_deg: float = 90.0, range_m: float = 40.0) -> None:
        """``world``: the ground image (``ground_image``); ``hood``: what stands on it."""
        self.world = world
        self.height, self.pitch = height_m, math.radians(pitch_deg)
        self.hfov, self.range = math.radians(hfov_deg), range_m
        self.fog_start = FOG_START * range_m
        parked = np.array([car.rectangle for car in hood.parked_cars]).reshape(-1, 5)
        houses = _houses(hood.houses)
        # Trees, then parked cars, then houses: the order in which objects that are
        # equally far are painted.
        cars = _face_parts(*_box_faces(parked, CAR_HEIGHT_M, PARKED_CAR))
        parts = _tree_parts(hood.trees).join(cars).join(_face_parts(*houses[:3]))
        extents = _tree_extents(hood.trees).join(_box_extents(parked, CAR_HEIGHT_M)).join(houses[3])
        counts = np.repeat([TREE_PARTS, FACES], [len(hood.trees), len(parked) + len(houses[0])])
        self.objects = _Set.of(extents, parts, counts)
        self.no_movers = _Set.of_movers(np.zeros((0, 5)))
        self.lenses: dict[tuple[int, int], _Lens] = {}

    def frame(self, x: float, y: float, heading: float, movers: np.ndarray | None = None) -> np.ndarray:
        """The observation at a pose: uint8 RGB, shape (66, 200, 3), a new array each call.

        ``movers``: traffic vehicles as rows (x, y, heading, length, width)."""
        return self.view(x, y, heading, FRAME_WIDTH, FRAME_HEIGHT, movers)

    def view(self, x: float, y: float, heading: float, columns: int, rows: int,
             movers: np.ndarray | None = None) -> np.ndarray:
        """The same camera at ``rows`` x ``columns`` pixels (pictures, ``render``): the field
        of view across is kept, pixels stay square and the crop's centre stays where it is."""
        lens = self.lens(columns, rows)
        pose = self.pose(x, y, heading)
        canvas = lens.background.copy()
        self._draw_ground(canvas, lens, pose)
        image = cv2.cvtColor(canvas, cv2.COLOR_RGBA2RGB)
        self._draw_objects(image, lens, pose, movers)
        return image

    def pose(self, x: float, y: float, heading: float) -> _Pose:
        c, s = math.cos(heading), math.sin(heading)
        cp, sp = math.cos(self.pitch), math.sin(self.pitch)
        h = self.height
        # Rows: the image's right, its down (world down tipped back by the pitch) and the
        # optical axis (forward tipped down by the pitch), each with its offset for the
        # camera at (x, y, h).
        to_camera = np.array([[-s, c, 0.0, s * x - c * y],
                              [-sp * c, -sp * s, -cp, sp * (c * x + s * y) + cp * h],
                              [cp * c, cp * s, -sp, sp * h - cp * (c * x + s * y)],
                              [0.0, 0.0, 0.0, 1.0]])
        return _Pose(np.array([x, y, h, 1.0]), to_camera, (c, s))

    # --- ground -----------------------------------------------------------------------------

    def _draw_ground(self, canvas: np.ndarray, lens: _Lens, pose: _Pose) -> None:
        band = canvas[lens.ground_top:]
        if not len(band):
            return
        cv2.warpPerspective(self.world.pixels, self._homography(lens, pose), band.shape[1::-1],
                            dst=band, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=(*GRASS, 0))
        fog = band[:len(lens.fog_ground)]
        if len(fog):
            cv2.blendLinear(fog, lens.haze_rows, lens.fog_ground, lens.fog_haze, dst=fog)

    def _homography(self, lens: _Lens, pose: _Pose) -> np.ndarray:
        """Band pixel to world-image pixel: pixel to ray, ray to where it meets the ground, ground
        to the world image's pixels."""
        x, y, height, _ = pose.position
        world, scale = self.world, self.world.scale
        # The ray p + t r meets z = 0 at p - height r / r_z: homogeneously (x r_z - height r_x, ...).
        ray_to_world = np.array([[-height * scale, 0.0, scale * (x - world.x_min) - 0.5],
                                 [0.0, -height * scale, scale * (y - world.y_min) - 0.5],
                                 [0.0, 0.0, 1.0]])
        return ray_to_world @ (pose.to_camera[:3, :3].T @ lens.from_band)

    # --- objects ----------------------------------------------------------------------------

    def _draw_objects(self, image: np.ndarray, lens: _Lens, pose: _Pose,
                      movers: np.ndarray | None) -> None:
        (fx, fy), (x, y, _, _) = pose.forward, pose.position
        # Rows of ``tests @ features``: the sphere centre's signed distance to the five
        # frustum planes; how far ahead the footprint's centre lies less its reach; the
        # footprint's axes against the heading; the camera's offset from the footprint's
        # centre along and across those axes.
        tests = np.empty((10, 9))
        tests[:5, :4] = lens.planes @ pose.to_camera
        tests[:5, 4:] = 0.0
        tests[5:] = (np.array([fx, fy, x, y, fx * x + fy * y, 1.0]) @ CULL_TERMS).reshape(5, 9)
        # Moving a point along the camera's right axis moves it along the camera's x only.
        projection = np.hstack([lens.to_fixed @ pose.to_camera[:3], lens.to_fixed[:, :1]])
        moving = self.no_movers if movers is None or not len(movers) else _Set.of_movers(movers)
        _paint(image, tests, pose.position, projection, lens.zoom * ONE, self.range, self.fog_start,
               HAZE_RGB, *self.objects.arrays, *moving.arrays)

    def _fog(self, ahead: np.ndarray) -> np.ndarray:
        """Weight of the haze, by how far ahead the ground or an object starts (1 beyond range)."""
        return np.clip((ahead - self.fog_start) / (self.range - self.fog_start), 0.0, 1.0)

    # --- per output size --------------------------------------------------------------------

    def lens(self, columns: int, rows: int) -> _Lens:
        if (columns, rows) not in self.lenses:
            self.lenses[columns, rows] = self._make_lens(columns, rows)
        return self.lenses[columns, rows]

    def _make_lens(self, columns: int, rows: int) -> _Lens:
        zoom = columns / FRAME_WIDTH
        focal = columns / 2 / math.tan(self.hfov / 2)
        # The sensor's centre lies SENSOR_ROWS / 2 - CROP_TOP_ROW frame rows below the
        # frame's top edge; another height keeps the crop's centre.
        centre_row = zoom * (SENSOR_ROWS / 2 - CROP_TOP_ROW) + (rows - zoom * FRAME_HEIGHT) / 2 - 0.5
        centre = ((columns - 1) / 2, centre_row)
        to_fixed = np.array([[ONE * focal, 0.0, ONE * centre[0]], [0.0, ONE * focal, ONE * centre_row],
                             [0.0, 0.0, 1.0]])
        slope = (np.arange(rows) - centre_row) / focal  # ray's y / z, per row
        cp, sp = math.cos(self.pitch), math.sin(self.pitch)
        down, forward = sp + slope * cp, cp - slope * sp  # of the row's central ray
        with np.errstate(divide="ignore"):
            ahead = np.where(down > 0, self.height * forward / down, np.inf)
        ground_top = int(np.searchsorted(-ahead, -self.range))  # ahead falls down the frame
        from_band = np.array([[1 / focal, 0.0, -centre[0] / focal],
                              [0.0, 1 / focal, (ground_top - centre_row) / focal],
                              [0.0, 0.0, 1.0]])
        fog = self._fog(ahead[ground_top:])
        fog = np.repeat(fog[:int(np.count_nonzero(fog)), None], columns, axis=1).astype(np.float32)
        haze_rows = np.zeros(fog.shape + (4,), dtype=np.uint8)
        haze_rows[..., :3] = HAZE
        return _Lens(zoom, to_fixed, ground_top, from_band,
                     _background(columns, np.degrees(np.arctan2(-down, forward))),
                     1 - fog, fog, haze_rows, _frustum(focal, centre, columns, rows))


# --- the compiled pass over the objects ---------------------------------------------------

@numba.njit(cache=True)
def _paint(image, tests, position, projection, min_size, range_m, fog_start, haze, *sets):
    """Culls the objects of both sets (static, movers) and paints the parts of those in view
    far to near (by the distance to their footprint; a stable sort keeps equally far ones in
    set order), each part faded into the haze by how far ahead its object starts."""
    # Each set is the 8 arrays of _Set.arrays: three for culling, the parts' first rows, then
    # four for drawing (literal slices: numba types a tuple's slice only by constants).
    statics, nearest_s, ahead_s = _visible(tests, range_m, *sets[:3])
    movers, nearest_m, ahead_m = _visible(tests, range_m, *sets[8:11])
    order = np.argsort(-np.concatenate((nearest_s, nearest_m)), kind="mergesort")
    fog = np.minimum(np.maximum((np.concatenate((ahead_s, ahead_m)) - fog_start) / (range_m - fog_start), 0.0), 1.0)
    scratch = np.empty((OUTLINE, 3)), np.empty(2 * OUTLINE, np.int64), np.empty(2 * OUTLINE, np.int64)
    for o in order:
        if o < len(statics):
            first, parts = sets[3], sets[4:8]
            i = statics[o]
        else:
            first, parts = sets[11], sets[12:16]
            i = movers[o - len(statics)]
        for p in range(first[i], first[i + 1]):
            _paint_part(image, position, projection, min_size, haze, fog[o], p, *parts, *scratch)


@numba.njit(cache=True)
def _visible(tests, range_m, features, radius, half):
    """Objects whose bounding sphere meets the frustum and whose footprint starts within the
    range: their index (ascending), the distance from the camera to the nearest point of
    their footprint, and how far ahead that footprint starts."""
    n = len(radius)
    index, nearest, ahead = np.empty(n, np.int64), np.empty(n), np.empty(n)
    values = np.empty(10)
    count = 0
    for i in range(n):
        outside = False
        for t in range(10):
            values[t] = 0.0
            for f in range(9):
                values[t] += tests[t, f] * features[i, f]
            if t < 5 and values[t] > radius[i]:  # beyond a frustum plane: most objects stop here
                outside = True
                break
        if outside:
            continue
        start = values[5] - abs(values[6]) * half[i, 0] - abs(values[7]) * half[i, 1]
        if start > range_m:
            continue
        gap_along, gap_across = max(abs(values[8]) - half[i, 0], 0.0), max(abs(values[9]) - half[i, 1], 0.0)
        index[count], ahead[count] = i, start
        nearest[count] = math.sqrt(gap_along * gap_along + gap_across * gap_across) - features[i, 8]
        count += 1
    return index[:count], nearest[:count], ahead[:count]


@numba.njit(cache=True)
def _paint_part(image, position, projection, min_size, haze, fog, p, points, planes, colours, kinds,
                projected, xs, ys):
    """One part: skipped if it faces away, is too close or too small, else projected, clipped
    to the near plane if it is a face that crosses it, and filled."""
    facing = 0.0
    for c in range(4):
        facing += planes[p, c] * position[c]
    if facing <= EDGE_ON:
        return
    crossing = False
    for k in range(OUTLINE):
        for r in range(3):
            projected[k, r] = 0.0
            for c in range(5):
                projected[k, r] += projection[r, c] * points[p, k, c]
        crossing = crossing or projected[k, 2] < NEAR_M
    disc, clearance, smallest = kinds[p, 0], kinds[p, 1], kinds[p, 2]
    if projected[0, 2] <= clearance or (crossing and clearance != -np.inf):
        return
    for k in range(OUTLINE):
        depth = max(projected[k, 2], NEAR_M)
        xs[k], ys[k] = round(projected[k, 0] / depth), round(projected[k, 1] / depth)
    size = abs(xs[1] - xs[0])  # a disc's radius, a trunk's width
    if size < smallest * min_size:
        return
    colour = np.empty(3, np.int64)
    for c in range(3):
        colour[c] = round(colours[p, c] + (haze[c] - colours[p, c]) * fog)
    if disc > 0:
        _fill_disc(image, xs[0], ys[0], size, colour)
    elif crossing:
        count = _clip(projected, xs, ys)
        if count >= 3:
            _fill_convex(image, xs, ys, count, colour)
    else:
        _fill_convex(image, xs, ys, OUTLINE, colour)


@numba.njit(cache=True)
def _clip(projected, xs, ys) -> int:
    """A face outline in (u z, v z, z) cut to z >= NEAR_M (the map from the world is linear, so
    cut points interpolate), divided through to fixed-point pixels in xs, ys; the vertex count."""
    count = 0
    for k in range(OUTLINE):
        following = (k + 1) % OUTLINE
        z0, z1 = projected[k, 2], projected[following, 2]
        if z0 >= NEAR_M:
            xs[count], ys[count] = round(projected[k, 0] / z0), round(projected[k, 1] / z0)
            count += 1
        if (z0 >= NEAR_M) != (z1 >= NEAR_M):
            t = (NEAR_M - z0) / (z1 - z0)
            u = projected[k, 0] + t * (projected[following, 0] - projected[k, 0])
            v = projected[k, 1] + t * (projected[following, 1] - projected[k, 1])
            xs[count], ys[count] = round(u / NEAR_M), round(v / NEAR_M)
            count += 1
    return count


# --- filling shapes ---------------------------------------------------------------------

@numba.njit(cache=True)
def _fill_span(image, row, left, right, colour) -> None:
    """Pixels of ``row`` whose centres lie within [left - GROW, right + GROW] (fixed point)."""
    first = max(0, -((-(left - GROW)) // ONE))  # ceil
    last = min(image.shape[1] - 1, (right + GROW) // ONE)
    for column in range(first, last + 1):
        image[row, column, 0] = colour[0]
        image[row, column, 1] = colour[1]
        image[row, column, 2] = colour[2]


@numba.njit(cache=True)
def _fill_convex(image, xs, ys, count, colour) -> None:
    """A convex polygon of ``count`` vertices (xs, ys: fixed point; repeats allowed), grown by
    GROW in x and in y: a row takes the polygon's span over the band GROW above and below it."""
    top, bottom = ys[0], ys[0]
    for k in range(1, count):
        top, bottom = min(top, ys[k]), max(bottom, ys[k])
    first = max(0, -((-(top - GROW)) // ONE))
    last = min(image.shape[0] - 1, (bottom + GROW) // ONE)
    for row in range(first, last + 1):
        # Over a band the span is widest at its edges or at a vertex inside it (convexity).
        low, high = min(max(row * ONE - GROW, top), bottom), min(max(row * ONE + GROW, top), bottom)
        left, right = _span(xs, ys, count, low)
        left_high, right_high = _span(xs, ys, count, high)
        left, right = min(left, left_high), max(right, right_high)
        for k in range(count):
            if low <= ys[k] <= high:
                left, right = min(left, xs[k]), max(right, xs[k])
        if left <= right:
            _fill_span(image, row, left, right, colour)


@numba.njit(cache=True)
def _span(xs, ys, count, y):
    """Where the line at height ``y`` (within the polygon's height) enters and leaves it."""
    left, right = 1 << 62, -(1 << 62)
    for k in range(count):
        x0, y0 = xs[k], ys[k]
        x1, y1 = xs[(k + 1) % count], ys[(k + 1) % count]
        if (y0 <= y <= y1) or (y1 <= y <= y0):
            if y0 == y1:
                left, right = min(left, x0, x1), max(right, x0, x1)
            else:
                x = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
                left, right = min(left, math.floor(x)), max(right, math.ceil(x))
    return left, right


@numba.njit(cache=True)
def _fill_disc(image, cx, cy, radius, colour) -> None:
    """A disc of centre (cx, cy) and ``radius``, all fixed point."""
    first = max(0, -((-(cy - radius - GROW)) // ONE))
    last = min(image.shape[0] - 1, (cy + radius + GROW) // ONE)
    for row in range(first, last + 1):
        dy = max(abs(row * ONE - cy) - GROW, 0)
        if dy > radius:
            continue
        half = int(math.sqrt(radius * radius - dy * dy))
        _fill_span(image, row, cx - half, cx + half, colour)


def _background(columns: int, elevation_deg: np.ndarray) -> np.ndarray:
    """Haze at and below the horizon, turning to SKY towards SKY_GRADIENT_DEG above it."""
    t = np.clip(elevation_deg / SKY_GRADIENT_DEG, 0.0, 1.0)[:, None]
    colours = np.rint(np.array(HAZE) * (1 - t) + np.array(SKY) * t).astype(np.uint8)
    background = np.zeros((len(elevation_deg), columns, 4), dtype=np.uint8)
    background[..., :3] = colours[:, None, :]
    return background


def _frustum(focal: float, centre: tuple[float, float], columns: int, rows: int) -> np.ndarray:
    """Unit-normal planes (camera coordinates) of the frame's four edges and the near plane."""
    left, right = (centre[0] + 0.5) / focal, (columns - 0.5 - centre[0]) / focal
    top, bottom = (centre[1] + 0.5) / focal, (rows - 0.5 - centre[1]) / focal
    sides = np.array([[1.0, 0.0, -right], [-1.0, 0.0, -left], [0.0, 1.0, -bottom], [0.0, -1.0, -top]])
    sides /= np.linalg.norm(sides, axis=1, keepdims=True)
    return np.vstack([np.column_stack([sides, np.zeros(4)]), [0.0, 0.0, -1.0, NEAR_M]])


# --- the objects ----------------------------------------------------------------------------

def _extents(centres: np.ndarray, radius: np.ndarray, headings: np.ndarray, half: np.ndarray,
             reach: np.ndarray) -> _Extents:
    """Culling rows of objects with bounding spheres (``centres``, ``radius``) over footprints
    centred below them: rectangles (``headings``, ``half``) widened all round by ``reach``."""
    cos, sin = np.cos(headings), np.sin(headings)
    x, y = centres[:, 0], centres[:, 1]
    features = np.vstack([centres.T, np.ones(len(x)), cos, sin, x * cos + y * sin, y * cos - x * sin, reach])
    return _Extents(features, radius, half.T.copy())


def _box_extents(rectangles: np.ndarray, height: float | np.ndarray) -> _Extents:
    """Culling rows of solids ``height`` tall on rectangles (x, y, heading, length, width)."""
    height = np.broadcast_to(np.asarray(height, dtype=np.float64), (len(rectangles),))
    half = rectangles[:, 3:5] / 2
    centres = np.column_stack([rectangles[:, :2], height / 2])
    radius = np.sqrt((half ** 2).sum(axis=1) + (height / 2) ** 2)
    return _extents(centres, radius, rectangles[:, 2], half, np.zeros(len(rectangles)))


def _box_faces(rectangles: np.ndarray, height: float,
               colour: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Outlines, planes and colours of boxes: the unit box moved into place by one affine map
    each, and its planes by the inverse map. (A loop, since a frame has only a few movers.)"""
    places, inverses, lights = [], [], []
    sun_x, sun_y, sun_z = SUN_XYZ
    for x, y, heading, length, width in rectangles.tolist():
        c, s = math.cos(heading), math.sin(heading)
        half_length, half_width = length / 2, width / 2
        places.append(((c * half_length, -s * half_width, 0.0, x), (s * half_length, c * half_width, 0.0, y),
                       (0.0, 0.0, height, 0.0), (0.0, 0.0, 0.0, 1.0)))
        inverses.append(((c / half_length, s / half_length, 0.0, -(c * x + s * y) / half_length),
                         (-s / half_width, c / half_width, 0.0, (s * x - c * y) / half_width),
                         (0.0, 0.0, 1.0 / height, 0.0), (0.0, 0.0, 0.0, 1.0)))
        # The sun against the outward normals: along, back, right, left, up, padding.
        along, across = c * sun_x + s * sun_y, c * sun_y - s * sun_x
        lights.append((along, -along, across, -across, sun_z, 0.0))
    light = AMBIENT + DIFFUSE * np.maximum(np.array(lights).reshape(-1, FACES), 0.0)
    outlines = (BOX_OUTLINES @ np.array(places).reshape(-1, 4, 4).transpose(0, 2, 1))
    return (outlines.reshape(-1, FACES, OUTLINE, 4), BOX_PLANES @ np.array(inverses).reshape(-1, 4, 4),
            np.multiply.outer(light, colour))


def _houses(houses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, _Extents]:
    """Outlines, planes, colours (as ``_box_faces``) and extents of houses on rectangles (x, y,
    heading, length, width): walls, then a gable roof whose ridge runs along the longer side."""
    houses = np.array(houses, dtype=np.float64)
    turned = houses[:, 4] > houses[:, 3]
    houses[turned, 2] += math.pi / 2
    houses[turned, 3:5] = houses[turned, 4:2:-1]
    n = len(houses)
    walls = np.resize(np.array(HOUSE_WALL_HEIGHTS_M), n)
    corners = rectangle_corners(houses)
    c, s, zero = np.cos(houses[:, 2]), np.sin(houses[:, 2]), np.zeros(n)
    along, across, up = (np.column_stack(v) for v in ((c, s, zero), (-s, c, zero), (zero, zero, zero + 1)))
    half_length = houses[:, None, 3:4] / 2
    ridge_ends = houses[:, None, :2] + np.stack([along[:, :2], -along[:, :2]], axis=1) * half_length
    vertices = np.concatenate([_lifted(corners, zero), _lifted(corners, walls),
                               _lifted(ridge_ends, walls + ROOF_RISE_M)], axis=1)
    half_width = houses[:, 4:5] / 2
    roofs = [ROOF_RISE_M * across + half_width * up, -ROOF_RISE_M * across + half_width * up]
    roofs = [roof / np.linalg.norm(roof, axis=1, keepdims=True) for roof in roofs]
    normals = np.stack([along, -along, across, -across, *roofs], axis=1)
    outlines = vertices[:, HOUSE_FACES]
    offsets = np.einsum("nfk,nfk->nf", normals, outlines[:, :, 0])
    light = AMBIENT + DIFFUSE * np.maximum(normals @ SUN, 0.0)
    colours = np.array([HOUSE_WALL] * 4 + [HOUSE_ROOF] * 2, dtype=np.float64)
    return (np.concatenate([outlines, np.ones(outlines.shape[:-1] + (1,))], axis=-1),
            np.concatenate([normals, -offsets[..., None]], axis=-1), light[..., None] * colours,
            _box_extents(houses, walls + ROOF_RISE_M))


def _face_parts(outlines: np.ndarray, planes: np.ndarray, colours: np.ndarray) -> _Parts:
    """The faces of solids (outlines, planes, colours, each over (solid, face)) as parts."""
    n = outlines.shape[0] * FACES
    points = np.concatenate([outlines, np.zeros(outlines.shape[:-1] + (1,))], axis=-1).reshape(n, OUTLINE, 5)
    kinds = np.broadcast_to([0.0, -np.inf, 0.0], (n, 3))
    return _Parts(points, planes.reshape(n, 4), colours.reshape(n, 3), kinds)


def _tree_parts(trees: np.ndarray) -> _Parts:
    """Each tree's trunk, canopy disc and the disc's sunlit side (shifted towards the sun, so
    it shows on the side the sun lights), from rows (x, y, canopy radius)."""
    n = len(trees)
    x, y, radii = trees.T
    centre = np.column_stack([x, y, np.full(n, CANOPY_CENTRE_M), np.ones(n)])
    foot = centre * (1.0, 1.0, 0.0, 1.0)
    lit = centre + np.append(HIGHLIGHT_SHIFT * SUN, 0.0) * radii[:, None]
    # Outlines: the trunk's foot left and right, its top right and left; a disc's centre,
    # then a point on its rim (repeated).
    rim = np.r_[0.0, np.ones(OUTLINE - 1)]
    trunk = _billboard(np.stack([foot, foot, centre, centre, centre], axis=1),
                       TRUNK_RADIUS_M * np.array([-1.0, 1.0, 1.0, -1.0, -1.0]))
    canopy = _billboard(np.repeat(centre[:, None], OUTLINE, axis=1), np.outer(radii, rim))
    sunlit = _billboard(np.repeat(lit[:, None], OUTLINE, axis=1), np.outer(HIGHLIGHT_RADIUS * radii, rim))
    always = np.broadcast_to([0.0, 0.0, 0.0, 1.0], (n * TREE_PARTS, 4))
    colours = np.broadcast_to(np.array([TRUNK, np.multiply(CANOPY, AMBIENT), CANOPY], dtype=np.float64),
                              (n, TREE_PARTS, 3))
    # A part is left out when it reaches the near plane: the tree then stands beside the
    # camera, outside the field of view (beyond the pavement, so at least a car's half width away).
    kinds = np.stack([np.column_stack([np.zeros(n), np.full(n, TRUNK_RADIUS_M + NEAR_M),
                                       np.full(n, TRUNK_MIN_PX)]),
                      np.column_stack([np.ones(n), radii + NEAR_M, np.zeros(n)]),
                      np.column_stack([np.ones(n), HIGHLIGHT_RADIUS * radii + NEAR_M,
                                       np.full(n, HIGHLIGHT_MIN_PX)])], axis=1)
    return _Parts(np.stack([trunk, canopy, sunlit], axis=1).reshape(-1, OUTLINE, 5), always,
                  colours.reshape(-1, 3), kinds.reshape(-1, 3))


def _billboard(anchors: np.ndarray, spread: np.ndarray) -> np.ndarray:
    """Homogeneous points (n, OUTLINE, 4), each with how far to move it along the camera's
    right axis (broadcast to (n, OUTLINE)), as ``_Parts.points``."""
    return np.concatenate([anchors, np.broadcast_to(spread, anchors.shape[:2])[..., None]], axis=-1)


def _tree_extents(trees: np.ndarray) -> _Extents:
    """Culling rows of trees at rows (x, y, canopy radius): the footprint is the canopy's circle."""
    n = len(trees)
    # The sphere through the trunk's foot and the canopy's top holds the whole
    # canopy too, as long as the canopy is clear of the ground.
    middle = (CANOPY_CENTRE_M + trees[:, 2]) / 2
    return _extents(np.column_stack([trees[:, :2], middle]), middle, np.zeros(n), np.zeros((n, 2)),
                    trees[:, 2])


def _lifted(points: np.ndarray, heights: np.ndarray) -> np.ndarray:
    """Ground points (n, k, 2) at one height per row as (n, k, 3)."""
    return np.concatenate([points, np.broadcast_to(heights[:, None, None], points.shape[:2] + (1,))], axis=2)


def front_strip(camera: PerspectiveCamera, poses, gap: int = 2) -> np.ndarray:
    """Frames at ``poses`` (x, y, heading), top to bottom, ``gap`` haze rows apart (pictures)."""
    separator = np.full((gap, FRAME_WIDTH, 3), HAZE, dtype=np.uint8)
    frames = [camera.frame(*pose) for pose in poses]
    return np.concatenate([part for f in frames for part in (f, separator)][:-1])
