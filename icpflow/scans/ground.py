"""Ground removal per scan (the teacher's step 2 and the student's input contract), on points in the height frame
of ``icpflow.scans.preprocess`` (ground near z = ``frame.ground_z``).

Settings: the ``ground`` block (``icpflow.teacher.config.GroundConfig``), read from a ``Preprocessing`` or a
teacher config. Methods (``ground.method``):

* ``local`` (the default): a point is ground when it lies at most ``margin`` above the local ground height, unless
  it stands inside or right under an object. The local ground height is a map of ``cell`` m cells built from
  Patchwork++'s ground points (the lowest per cell), taken as its lower envelope under a ``slope`` (no cell stands
  higher than another plus ``slope`` times their distance: a roof or a bonnet that Patchwork++ took for ground falls
  out); a cell without such points takes the nearest one's height within ``FILL_REACH``; where there is none (beyond
  Patchwork++'s range), Patchwork++'s own verdict stands. Objects: a point called ground with a non-ground point
  within ``column_radius`` (horizontally) that starts at most ``column_gap`` above the ground (a leg, a wheel, a
  bumper; not a tree's crown) is kept with that object. Nothing moving is cut at a fixed height: the lower 0.34 m of
  every vehicle and a pedestrian's legs, which the z threshold took, stay with their object (BENCHMARKS.md, "Ground
  that keeps moving objects").
* ``patchwork`` (Patchwork++, ``pypatchworkpp``, on the scan shifted so that the ground sits at -sensor_height),
  ``zthreshold`` (ground if ``z <= range_z + slack``), ``both`` (a point is non-ground only if both say so: the
  reference's, and that of every model stored before ``local``) and ``none``.
"""

from __future__ import annotations

import numba
import numpy as np

from icpflow.core.console import captured_output
from icpflow.scans.preprocess import Preprocessing

#: metres: a cell of the ground-height map without ground points takes the height of the nearest cell with some,
#: at most this far
FILL_REACH = 4.0
#: metres: beyond the ground-height map, the odometry's surface mask takes the points up to this far above the frame's
#: ground plane (the far rings of the ground, which Patchwork++ does not reach, are the sensor's pattern too)
FAR_SLACK = 0.3
#: a ground seed lies at most DROP_M + DROP_GRADE x its horizontal range below the frame's ground plane: a 15 % fall
#: over the whole range, and a metre more (:func:`below_any_road`)
DROP_M = 1.0
DROP_GRADE = 0.15


class GroundSegmenter:
    """Ground masks for one configuration.

    Patchwork++ adapts its elevation and flatness thresholds to the scans it has seen (a ``patchworkpp`` object
    gives a different mask for the same scan the second time), so every scan gets a fresh object (about 20 us):
    a pair's ground then depends on that pair alone, whatever order or worker labels it.
    """

    def __init__(self, cfg):
        """``cfg``: a :class:`~icpflow.scans.preprocess.Preprocessing` or a teacher config (``ICPFlowConfig``)."""
        self.settings = cfg if isinstance(cfg, Preprocessing) else Preprocessing.from_teacher(cfg)
        ground = self.settings.ground
        self._params = None
        if ground.method in ("both", "patchwork", "local"):
            import pypatchworkpp

            params = pypatchworkpp.Parameters()
            params.verbose = False
            params.enable_RNR = False  # intensity-based noise removal: we pass no intensity
            params.intensity_thr = 0.0  # left uninitialised by the binding
            params.sensor_height = float(ground.sensor_height)
            params.min_range = 1.0
            params.max_range = float(ground.patchwork_max_range)
            self._params = params

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool ground mask of (N, 3) float32 points."""
        n = len(points)
        ground = np.zeros(n, dtype=bool)
        settings = self.settings.ground
        if n == 0 or settings.method == "none":
            return ground
        if settings.method == "local":
            return self.local(points)
        if settings.method in ("both", "zthreshold"):
            ground |= points[:, 2] <= settings.range_z + settings.slack
        if self._params is not None:
            ground |= self.patchwork(points)
        return ground

    def patchwork(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool Patchwork++ ground mask."""
        ground = np.zeros(len(points), dtype=bool)
        if len(points) < 10:
            return ground
        cloud = np.zeros((len(points), 4), dtype=np.float64)  # x, y, z, intensity (unused)
        cloud[:, :3] = points
        cloud[:, 2] += self.settings.patchwork_z_offset
        import pypatchworkpp

        with captured_output((1,)):  # Patchwork++'s constructor prints even when not verbose
            patchwork = pypatchworkpp.patchworkpp(self._params)
        patchwork.estimateGround(cloud)
        ground[np.asarray(patchwork.getGroundIndices(), dtype=np.int64)] = True
        return ground

    def masks(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(ground, surface), each (N,) bool, of (N, 3) float32 points: ``ground`` what the teacher and the network
        leave out (this segmenter's mask); ``surface`` every point of the ground's surface, objects' feet included
        (the ``local`` method's points at most ``margin`` above the local ground, before the object columns; the
        ground itself for the other methods), what the odometry leaves out: a ring of ground points at a wall's or
        a car's foot is drawn by the sensor, and pulls a registration towards the identity (a 64-beam drive along a
        bare street drifted 30-60 cm with them; BENCHMARKS.md, "One odometry")."""
        if self.settings.ground.method != "local" or len(points) == 0:
            ground = self(points)
            return ground, ground
        settings = self.settings.ground
        seeds = self.patchwork(points) & ~below_any_road(points, self.settings.frame.ground_z)
        height = points[:, 2] - ground_height(
            points, seeds, settings.cell, settings.slope, settings.patchwork_max_range
        )
        known = np.isfinite(height)
        surface = np.where(known, height <= settings.margin, seeds)
        height = np.where(known, height, np.inf)  # no ground near: no object column either
        ground = surface & ~object_columns(points, surface, height, settings.column_radius, settings.column_gap)
        # beyond the map (Patchwork++'s range) the surface is also the frame's plane, give or take FAR_SLACK
        return ground, surface | (~known & (points[:, 2] <= self.settings.frame.ground_z + FAR_SLACK))

    def local(self, points: np.ndarray) -> np.ndarray:
        """(N,) bool mask of the ``local`` method (module docstring)."""
        return self.masks(points)[0]


def below_any_road(points: np.ndarray, ground_z: float) -> np.ndarray:
    """(N,) bool: points further below the frame's ground plane (``ground_z``) than any road falls, more than
    :data:`DROP_M` plus :data:`DROP_GRADE` of their horizontal range. Patchwork++ can call such returns (a reflection
    through a grate, multipath) ground; as the local map's lowest seeds they would pull the ground under every
    point around them metres down, and nothing would be ground there."""
    reach = np.hypot(points[:, 0], points[:, 1])
    return points[:, 2] < ground_z - DROP_M - DROP_GRADE * reach


def ground_height(points: np.ndarray, seeds: np.ndarray, cell: float, slope: float, reach: float) -> np.ndarray:
    """(N,) float32 local ground height (z, m) below each of the (N, 3) ``points`` from the (N,) bool ``seeds``
    (Patchwork++'s ground points): a map of ``cell`` m cells over |x|, |y| < ``reach``, each the lowest seed in it,
    then its lower envelope under ``slope`` m per m; a cell without seeds takes the nearest seeded cell's height
    within ``FILL_REACH``; NaN where no seed is that near and outside the map."""
    points = np.ascontiguousarray(points, np.float32)
    return _ground_height(points, np.asarray(seeds, bool), float(cell), float(slope), float(reach), FILL_REACH)


def object_columns(points: np.ndarray, ground: np.ndarray, height: np.ndarray, radius: float, gap: float):
    """(N,) bool: the points of ``ground`` (N,) bool that stand inside or right under an object, i.e. within
    ``radius`` m (horizontally) of a non-ground point at most ``gap`` m above the local ground (``height`` (N,)
    float32: each point's height above it, inf where unknown)."""
    points = np.ascontiguousarray(points, np.float32)
    return _object_columns(points, np.asarray(ground, bool), np.asarray(height, np.float32), float(radius), float(gap))


@numba.njit(cache=True, nogil=True)
def _ground_height(points, seeds, cell, slope, reach, fill_reach):
    size = int(np.ceil(2.0 * reach / cell))
    n = len(points)
    cells = np.full(n, -1, np.int64)
    height = np.full((size, size), np.inf, np.float32)
    for i in range(n):
        cx = int(np.floor((points[i, 0] + reach) / cell))
        cy = int(np.floor((points[i, 1] + reach) / cell))
        if 0 <= cx < size and 0 <= cy < size:
            cells[i] = cx * size + cy
            if seeds[i] and points[i, 2] < height[cx, cy]:
                height[cx, cy] = points[i, 2]
    seeded = np.isfinite(height)
    # two raster passes (forward, then backward) over 8-neighbour steps (d: the chamfer distance): first the lower
    # envelope min over cells m of (lowest(m) + slope * d(m, c)), then each hole's nearest seeded cell
    straight, diagonal = np.float32(cell), np.float32(cell * np.sqrt(2.0))
    distance = np.where(seeded, np.float32(0.0), np.float32(np.inf))
    for envelope in (True, False):
        for backward in (False, True):
            sign = -1 if backward else 1
            for step in range(size):
                cx = size - 1 - step if backward else step
                for inner in range(size):
                    cy = size - 1 - inner if backward else inner
                    if not envelope and seeded[cx, cy]:
                        continue
                    for dx, dy in ((-1, -1), (-1, 0), (-1, 1), (0, -1)):
                        nx, ny = cx + sign * dx, cy + sign * dy
                        if nx < 0 or ny < 0 or nx >= size or ny >= size:
                            continue
                        length = diagonal if dx != 0 and dy != 0 else straight
                        if envelope:
                            rise = height[nx, ny] + slope * length
                            if rise < height[cx, cy]:
                                height[cx, cy] = rise
                        elif distance[nx, ny] + length < distance[cx, cy]:
                            distance[cx, cy] = distance[nx, ny] + length
                            height[cx, cy] = height[nx, ny]
    out = np.full(n, np.nan, np.float32)
    for i in range(n):
        if cells[i] >= 0:
            cx, cy = cells[i] // size, cells[i] % size
            if distance[cx, cy] <= fill_reach:
                out[i] = height[cx, cy]
    return out


@numba.njit(cache=True, nogil=True)
def _object_columns(points, ground, height, radius, gap):
    n = len(points)
    out = np.zeros(n, np.bool_)
    # the low non-ground points, listed per cell of a grid over their bounding box
    cell = max(radius, 0.25)
    low = np.zeros(n, np.bool_)
    count = 0
    x0, y0, x1, y1 = np.inf, np.inf, -np.inf, -np.inf
    for i in range(n):
        if not ground[i] and height[i] <= gap:
            low[i] = True
            count += 1
            x0, y0 = min(x0, points[i, 0]), min(y0, points[i, 1])
            x1, y1 = max(x1, points[i, 0]), max(y1, points[i, 1])
    if count == 0:
        return out
    nx, ny = int((x1 - x0) / cell) + 1, int((y1 - y0) / cell) + 1
    head = np.full(nx * ny, -1, np.int64)
    following = np.full(n, -1, np.int64)
    for i in range(n):
        if low[i]:
            key = int((points[i, 0] - x0) / cell) * ny + int((points[i, 1] - y0) / cell)
            following[i] = head[key]
            head[key] = i
    limit = radius * radius
    for i in range(n):
        if not ground[i]:
            continue
        cx = int(np.floor((points[i, 0] - x0) / cell))
        cy = int(np.floor((points[i, 1] - y0) / cell))
        found = False
        for ax in range(max(cx - 1, 0), min(cx + 2, nx)):
            for ay in range(max(cy - 1, 0), min(cy + 2, ny)):
                j = head[ax * ny + ay]
                while j >= 0:
                    dx, dy = points[j, 0] - points[i, 0], points[j, 1] - points[i, 1]
                    if dx * dx + dy * dy <= limit:
                        found = True
                        break
                    j = following[j]
                if found:
                    break
            if found:
                break
        out[i] = found
    return out
