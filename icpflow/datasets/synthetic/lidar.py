"""A spinning LiDAR ray-caster over a :class:`~icpflow.datasets.synthetic.scene.Scene`, vectorised in numpy.

Ego frame (what scans are expressed in): origin on the ground under the sensor, x forward, y left, z up, tilted
with the road plane (``Scene.ego_poses`` is world_from_ego). The sensor sits at (0, 0, ``height``) in the ego
frame with its axes parallel to the ego's. Each scan is instantaneous at its frame's timestamp (no rolling shutter).

Rays: ``beams`` elevations spread evenly over ``elevation_deg`` (low, high) times azimuth columns every
``azimuth_resolution_deg`` from -180 degrees. Each ray returns its nearest hit among the ground height field and
every primitive (exact analytic boxes, cylinders and ellipsoids; the ground by a bracketed sign search and
bisection), if nearer than ``max_range``. Range noise (Gaussian, ``range_noise`` m) moves a point along its ray;
``dropout`` is the probability that a ray returns nothing. Primitives are culled per scan by the azimuth and
elevation interval of their bounding sphere, so each one is tested only against the rays that can reach it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from icpflow.core.geometry import invert
from icpflow.datasets.synthetic.scene import BOX, CYLINDER, ELLIPSOID, Scene
from icpflow.scans.preprocess import DEFAULT_SENSOR_HEIGHT

#: (low, high) elevation in degrees per beam count: Waymo-like 64 beams, nuScenes-like 32 beams
ELEVATIONS = {64: (-17.6, 2.4), 32: (-30.0, 10.0)}
EPS = 1e-6


#: metres of the synthetic world's sensor above the ego origin, which lies on the ground: the default height frame's
#: (``icpflow.scans.preprocess.DEFAULT_SENSOR_HEIGHT``, written there only)
SENSOR_HEIGHT = DEFAULT_SENSOR_HEIGHT


@dataclass(frozen=True)
class Lidar:
    """Sensor settings (metres, degrees); see the module docstring."""

    beams: int = 64
    elevation_deg: tuple[float, float] | None = None  # None: ELEVATIONS[beams] (else (-25, 5))
    azimuth_resolution_deg: float = 0.2
    max_range: float = 75.0
    range_noise: float = 0.02
    dropout: float = 0.03
    height: float = SENSOR_HEIGHT
    ground_samples: int = 8
    ground_bisections: int = 16

    def __post_init__(self):
        if self.beams < 1 or not 0 < self.azimuth_resolution_deg <= 10 or self.max_range <= 0:
            raise ValueError(f"Lidar: bad beams / azimuth resolution / max range: {self}")
        if self.range_noise < 0 or not 0 <= self.dropout < 1 or self.height <= 0:
            raise ValueError(f"Lidar: bad range noise / dropout / height: {self}")

    def elevations(self) -> np.ndarray:
        """(B,) beam elevations in radians, ascending."""
        low, high = self.elevation_deg or ELEVATIONS.get(self.beams, (-25.0, 5.0))
        return np.deg2rad(np.linspace(low, high, self.beams))

    def azimuths(self, offset: float = 0.0) -> np.ndarray:
        """(C,) column azimuths in radians, column j at ``-pi + (j + offset) * resolution``."""
        count = int(round(360.0 / self.azimuth_resolution_deg))
        return -np.pi + (np.arange(count) + offset) * (2 * np.pi / count)

    def directions(self, offset: float = 0.0) -> np.ndarray:
        """(B, C, 3) unit ray directions in the sensor (= ego) axes; ``offset`` as in ``azimuths``."""
        el, az = self.elevations()[:, None], self.azimuths(offset)[None, :]
        return np.stack(np.broadcast_arrays(np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), -1)


@dataclass
class Scan:
    """One scan: ``points`` (N, 3) float32 in the ego frame; per point ``primitive`` int32 (0 = ground, p + 1 =
    scene primitive p), ``beam`` and ``column`` int32 (the ray: ``Lidar.directions(azimuth_offset)[beam, column]``),
    ``range`` float64 (measured, m); ``azimuth_offset`` in columns, the spin phase of this scan."""

    points: np.ndarray
    primitive: np.ndarray
    beam: np.ndarray
    column: np.ndarray
    range: np.ndarray
    azimuth_offset: float = 0.0


def intersect(kind: int, size: np.ndarray, origin: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Ray parameter of the first hit (> EPS) of rays ``origin + t d`` with one primitive, in its own frame.

    ``origin`` (3,), ``directions`` (M, 3) unit; returns (M,) float64, inf where a ray misses.
    """
    o, d = origin, directions
    with np.errstate(divide="ignore", invalid="ignore"):
        if kind == BOX:
            inverse = 1.0 / d
            t1, t2 = (-size - o) * inverse, (size - o) * inverse
            near = np.minimum(t1, t2).max(1)
            far = np.maximum(t1, t2).min(1)
            return np.where((near <= far) & (near > EPS), near, np.inf)
        if kind == ELLIPSOID:
            o, d = o / size, d / size
            a, b, c = (d * d).sum(1), 2 * d @ o, o @ o - 1.0
            disc = b * b - 4 * a * c
            t = (-b - np.sqrt(disc)) / (2 * a)
            return np.where((disc >= 0) & (t > EPS), t, np.inf)
        if kind == CYLINDER:
            radius, half = size[0], size[2]
            dxy = d[:, :2]
            a, b, c = (dxy * dxy).sum(1), 2 * dxy @ o[:2], o[:2] @ o[:2] - radius**2
            disc = b * b - 4 * a * c
            t = (-b - np.sqrt(disc)) / (2 * a)
            z = o[2] + t * d[:, 2]
            side = np.where((disc >= 0) & (a > 0) & (t > EPS) & (np.abs(z) <= half), t, np.inf)
            caps = []
            for level in (-half, half):
                t = (level - o[2]) / d[:, 2]
                xy = o[:2] + t[:, None] * dxy
                caps.append(np.where((t > EPS) & ((xy * xy).sum(1) <= radius**2), t, np.inf))
            return np.minimum(side, np.minimum(*caps))
    raise ValueError(f"intersect: unknown primitive kind {kind}")


def surface_distance(kind: int, size: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(M,) distance of (M, 3) points (primitive frame) to the primitive's surface; first-order for ellipsoids."""
    p = np.asarray(points, np.float64)
    if kind == BOX:
        q = np.abs(p) - size
        return np.abs(np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0))
    if kind == CYLINDER:
        q = np.stack([np.hypot(p[:, 0], p[:, 1]) - size[0], np.abs(p[:, 2]) - size[2]], 1)
        return np.abs(np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0))
    if kind == ELLIPSOID:
        value = ((p / size) ** 2).sum(1) - 1.0
        return np.abs(value) / np.linalg.norm(2 * p / size**2, axis=1)
    raise ValueError(f"surface_distance: unknown primitive kind {kind}")


def _ground(
    scene: Scene, sensor_in_world: np.ndarray, directions: np.ndarray, limit: np.ndarray, lidar: Lidar
) -> np.ndarray:
    """(M,) ray parameter of the first ground hit of world rays from ``sensor_in_world`` (3,) nearer than
    ``limit`` (M,), inf if none.

    ``f(t) = z(t) - height(x(t), y(t))`` is positive above the ground. With ``height = plane + detail`` and
    ``detail`` in [lo, hi], the first root lies in [t_hi, t_lo] where the ray meets plane + hi and plane + lo; a
    sign search over ``ground_samples`` points there, then bisection, finds it (kerb faces included).
    """
    g = scene.ground
    lo, hi = g.detail_bounds()
    o, d = sensor_in_world, directions
    above = o[2] - g.plane(o[0], o[1])  # sensor height over the plane
    descent = -(d[:, 2] - g.slope[0] * d[:, 0] - g.slope[1] * d[:, 1])  # > 0: the ray approaches the plane
    t = np.full(len(d), np.inf)
    rays = np.flatnonzero(descent > 1e-9)
    if not len(rays):
        return t
    dr, rate = d[rays], descent[rays]
    start, stop = (above - hi) / rate, np.minimum((above - lo) / rate, limit[rays])
    keep = start < stop
    rays, dr, start, stop = rays[keep], dr[keep], start[keep], stop[keep]

    dx, dy, dz = dr.T.copy()

    def f(s, subset):
        return o[2] + s * dz[subset] - g.height(o[0] + s * dx[subset], o[1] + s * dy[subset])

    low, high = start.copy(), np.full(len(rays), np.inf)
    search = np.arange(len(rays))  # rays still above the ground at every sample so far
    for step in np.linspace(0.0, 1.0, lidar.ground_samples + 1)[1:]:
        s = start[search] + step * (stop[search] - start[search])
        below = f(s, search) <= 0
        high[search[below]] = s[below]
        low[search[~below]] = s[~below]
        search = search[~below]
    hit = np.isfinite(high)
    rays, dx, dy, dz, low, high = rays[hit], dx[hit], dy[hit], dz[hit], low[hit], high[hit]
    for _ in range(lidar.ground_bisections):
        mid = 0.5 * (low + high)
        below = f(mid, slice(None)) <= 0
        high = np.where(below, mid, high)
        low = np.where(below, low, mid)
    t[rays] = high
    return t


def cast(scene: Scene, frame: int, lidar: Lidar, rng: np.random.Generator | None = None) -> Scan:
    """Ray-cast the scene at ``frame``. ``rng`` draws the spin phase (an azimuth offset of 0 to 1 column, so two
    scans do not sample the same azimuths), then range noise and dropout; None: phase 0, noise-free, no dropout."""
    offset = float(rng.random()) if rng is not None else 0.0
    directions = lidar.directions(offset)  # (B, C, 3), sensor axes = ego axes
    beams, columns = directions.shape[:2]
    elevation, res = lidar.elevations(), 2 * np.pi / columns
    world_from_sensor = scene.ego_poses[frame].copy()
    world_from_sensor[:3, 3] += lidar.height * world_from_sensor[:3, 2]
    sensor_from_world = invert(world_from_sensor)

    best = np.full((beams, columns), np.inf)
    best_id = np.zeros((beams, columns), np.int32)

    poses = sensor_from_world @ scene.primitive_poses(frame)  # (P, 4, 4) sensor_from_primitive
    centre = poses[:, :3, 3]
    radius = np.linalg.norm(scene.size, axis=1)
    cylinder, ellipsoid = scene.kind == CYLINDER, scene.kind == ELLIPSOID
    radius[cylinder] = np.hypot(scene.size[cylinder, 0], scene.size[cylinder, 2])
    radius[ellipsoid] = scene.size[ellipsoid].max(1)
    distance = np.linalg.norm(centre, axis=1)
    horizontal = np.hypot(centre[:, 0], centre[:, 1])
    for p in np.flatnonzero(distance - radius < lidar.max_range):
        if distance[p] > radius[p]:
            half_el = np.arcsin(radius[p] / distance[p])
            el = np.arctan2(centre[p, 2], horizontal[p])
            rows = np.arange(
                np.searchsorted(elevation, el - half_el), np.searchsorted(elevation, el + half_el, "right")
            )
        else:
            rows = np.arange(beams)
        if horizontal[p] > radius[p] and len(rows):
            half_az = np.arcsin(radius[p] / horizontal[p])
            az = np.arctan2(centre[p, 1], centre[p, 0])
            first = np.floor((az - half_az + np.pi) / res - offset)
            last = np.ceil((az + half_az + np.pi) / res - offset)
            cols = np.arange(int(first), int(last) + 1) % columns
        else:
            cols = np.arange(columns)
        if not len(rows):
            continue
        block = np.ix_(rows, cols)
        rotation = poses[p, :3, :3]
        origin = -rotation.T @ poses[p, :3, 3]  # the sensor in the primitive frame
        t = intersect(int(scene.kind[p]), scene.size[p], origin, directions[block].reshape(-1, 3) @ rotation)
        t = t.reshape(len(rows), len(cols))
        current = best[block]
        nearer = t < current
        if nearer.any():
            best[block] = np.where(nearer, t, current)
            best_id[block] = np.where(nearer, p + 1, best_id[block])

    world_dirs = directions.reshape(-1, 3) @ world_from_sensor[:3, :3].T
    limit = np.minimum(best, lidar.max_range).reshape(-1)
    ground = _ground(scene, world_from_sensor[:3, 3], world_dirs, limit, lidar).reshape(beams, columns)
    best_id[ground < best] = 0
    best = np.minimum(ground, best)
    valid = best < lidar.max_range
    measured = best
    if rng is not None:
        measured = best + rng.normal(0.0, 1.0, best.shape) * lidar.range_noise  # drawn whatever the settings
        valid &= (rng.random(best.shape) >= lidar.dropout) & (measured > 0)
    beam, column = np.nonzero(valid)
    ranges = measured[beam, column]
    points = directions[beam, column] * ranges[:, None]
    points[:, 2] += lidar.height
    return Scan(
        points=points.astype(np.float32),
        primitive=best_id[beam, column],
        beam=beam.astype(np.int32),
        column=column.astype(np.int32),
        range=ranges,
        azimuth_offset=offset,
    )
