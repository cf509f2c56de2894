"""A seeded street world for the synthetic LiDAR: ground, static structures, parked and moving agents, the ego.

World frame: metres, z up. The main road runs along world x (|y| < ``ROAD_HALF``: two 3.5 m lanes each way and a
2.5 m parking lane per side, right-hand traffic), a cross street runs along y at ``x = cross_x``; sidewalks behind
kerbs, then building walls. The ground is a height field (a gentle plane, a few long low sinusoids, kerb steps).

Every shape is a primitive rigidly attached to an *owner*: owner 0 is the static world (ground-standing
structures: instance 0, class 0); owner i >= 1 is agent i with its own instance id, class and per-frame pose
``world_from_owner`` (T, 4, 4). Parked vehicles and standing pedestrians are agents with a constant pose.

Primitives (arrays over P shapes; primitive id ``p + 1`` in scans, 0 is the ground):
* ``kind`` 0 box (size = half extents), 1 vertical cylinder (size = radius, radius, half height), 2 ellipsoid
  (size = semi-axes); each centred at its own origin, placed by ``local`` (P, 4, 4) ``owner_from_primitive``.

The ego frame (see ``icpflow.datasets.synthetic.lidar``): origin on the ground under the sensor, x forward, y left, z
up, tilted with the road plane; the ego pose ``world_from_ego`` is given per frame.

Class table (``CLASSES``; ``AV2_META_CLASSES`` maps each onto the AV2 bucketed-metric meta-classes).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CLASSES = {0: "background", 1: "car", 2: "other_vehicle", 3: "pedestrian", 4: "cyclist"}
AV2_META_CLASSES = {0: "BACKGROUND", 1: "CAR", 2: "OTHER_VEHICLES", 3: "PEDESTRIAN", 4: "WHEELED_VRU"}
CAR, OTHER_VEHICLE, PEDESTRIAN, CYCLIST = 1, 2, 3, 4
BOX, CYLINDER, ELLIPSOID = 0, 1, 2

ROAD_HALF = 9.5
CROSS_HALF = 7.0
SIDEWALK = 4.5
LANES = (-5.25, -1.75, 1.75, 5.25)
PARKING = 8.25


@dataclass(frozen=True)
class Ground:
    """Height field ``z(x, y) = slope . (x, y) + offset + waves + kerb * off_road`` (world frame, metres)."""

    slope: tuple[float, float]
    offset: float
    amplitudes: np.ndarray  # (W,) metres
    waves: np.ndarray  # (W, 2) rad per metre
    phases: np.ndarray  # (W,)
    kerb: float
    cross_x: float

    def plane(self, x, y):
        return self.slope[0] * x + self.slope[1] * y + self.offset

    def detail(self, x, y):
        """Height above the plane: waves, plus the kerb step off the road."""
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        height = np.zeros(np.broadcast(x, y).shape)
        for amplitude, (kx, ky), phase in zip(self.amplitudes, self.waves, self.phases):
            height += amplitude * np.sin((kx * x + ky * y + phase).astype(np.float32))  # float32 sine: ~1e-6 m
        off_road = (np.abs(y) >= ROAD_HALF) & (np.abs(x - self.cross_x) >= CROSS_HALF)
        return height + self.kerb * off_road

    def height(self, x, y):
        return self.plane(x, y) + self.detail(x, y)

    def detail_bounds(self) -> tuple[float, float]:
        """(min, max) of ``detail`` over the whole plane."""
        total = float(np.sum(self.amplitudes))
        return -total, total + self.kerb

    def orientation(self, yaw) -> np.ndarray:
        """(..., 3, 3) rotations with z along the plane normal and x along heading ``yaw`` in the plane."""
        yaw = np.asarray(yaw, np.float64)
        a, b = self.slope
        forward = np.stack([np.cos(yaw), np.sin(yaw), a * np.cos(yaw) + b * np.sin(yaw)], -1)
        forward /= np.linalg.norm(forward, axis=-1, keepdims=True)
        up = np.broadcast_to(np.array([-a, -b, 1.0]) / np.hypot(np.hypot(a, b), 1.0), forward.shape)
        left = np.cross(up, forward)
        return np.stack([forward, left, up], -1)


@dataclass
class Scene:
    """A seeded world over ``T`` frames (see the module docstring for frames and arrays)."""

    seed: int
    timestamps_ns: np.ndarray  # (T,) int64
    ego_poses: np.ndarray  # (T, 4, 4) world_from_ego
    ground: Ground
    owner_poses: np.ndarray  # (O, T, 4, 4) world_from_owner; owner 0 = identity
    owner_instance: np.ndarray  # (O,) int32, 0 for owner 0
    owner_class: np.ndarray  # (O,) int32
    owner_speed: np.ndarray  # (O,) float64 nominal speed (m/s)
    kind: np.ndarray  # (P,) int8
    owner: np.ndarray  # (P,) int32
    local: np.ndarray  # (P, 4, 4) owner_from_primitive
    size: np.ndarray  # (P, 3)

    @property
    def frames(self) -> int:
        return len(self.timestamps_ns)

    def primitive_poses(self, t: int) -> np.ndarray:
        """(P, 4, 4) world_from_primitive at frame t."""
        return self.owner_poses[self.owner, t] @ self.local

    def labels(self, primitive: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(classes, instance) int32 per hit from primitive ids (0 = ground)."""
        classes = np.r_[0, self.owner_class[self.owner]].astype(np.int32)
        instance = np.r_[0, self.owner_instance[self.owner]].astype(np.int32)
        return classes[primitive], instance[primitive]

    def object_poses(self) -> dict[int, np.ndarray]:
        """Instance id -> (T, 4, 4) world_from_object, for every agent."""
        return {int(self.owner_instance[o]): self.owner_poses[o] for o in range(1, len(self.owner_instance))}


def _transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    out = np.zeros(rotation.shape[:-2] + (4, 4))
    out[..., :3, :3] = rotation
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def _local(x=0.0, y=0.0, z=0.0, yaw=0.0) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0, x], [s, c, 0, y], [0, 0, 1, z], [0, 0, 0, 1]], np.float64)


def _box(length, width, z0, z1, x=0.0, y=0.0, yaw=0.0):
    return BOX, _local(x, y, (z0 + z1) / 2, yaw), (length / 2, width / 2, (z1 - z0) / 2)


def _cylinder(radius, z0, z1, x=0.0, y=0.0):
    return CYLINDER, _local(x, y, (z0 + z1) / 2), (radius, radius, (z1 - z0) / 2)


def _ellipsoid(rx, ry, rz, x=0.0, y=0.0, z=0.0, yaw=0.0):
    return ELLIPSOID, _local(x, y, z, yaw), (rx, ry, rz)


def agent_shapes(cls: int, rng: np.random.Generator) -> tuple[list, tuple[float, float]]:
    """Primitives of one agent in its own frame (origin on the ground at the footprint centre, x forward) and
    the footprint half (length, width)."""
    if cls == CAR:
        length, width = rng.uniform(4.1, 4.9), rng.uniform(1.75, 1.95)
        roof = rng.uniform(1.4, 1.6)
        shapes = [_box(length, width, 0.2, 0.95), _box(length * 0.55, width * 0.92, 0.95, roof, x=-0.1 * length)]
    elif cls == OTHER_VEHICLE:
        kind = rng.integers(3)
        if kind == 0:  # van
            length, width, height = rng.uniform(5.0, 6.0), 2.0, rng.uniform(2.2, 2.6)
            shapes = [
                _box(length, width, 0.25, height * 0.5),
                _box(length * 0.8, width, height * 0.5, height, x=-0.1 * length),
            ]
        elif kind == 1:  # truck: cab and cargo box
            cargo, width = rng.uniform(6.0, 8.5), 2.5
            length = cargo + 2.6
            shapes = [
                _box(2.3, width, 0.4, 3.0, x=length / 2 - 1.15),
                _box(cargo, width, 0.6, rng.uniform(3.3, 3.8), x=-length / 2 + cargo / 2),
            ]
        else:  # bus
            length, width = rng.uniform(10.0, 12.0), 2.55
            shapes = [_box(length, width, 0.3, rng.uniform(3.0, 3.3))]
    elif cls == PEDESTRIAN:
        height, radius = rng.uniform(1.55, 1.9), rng.uniform(0.2, 0.28)
        length = width = 2 * radius
        shapes = [_cylinder(radius, 0.0, height - 0.25), _ellipsoid(0.11, 0.11, 0.13, z=height - 0.13)]
    elif cls == CYCLIST:
        length, width = 1.8, 0.6
        shapes = [
            _box(1.75, 0.12, 0.05, 0.95),
            _cylinder(0.22, 0.95, 1.55, x=-0.15),
            _ellipsoid(0.12, 0.12, 0.14, x=-0.05, z=1.7),
        ]
    else:
        raise ValueError(f"agent_shapes: unknown class {cls}")
    return shapes, (length / 2, width / 2)


def _corners(centre, yaw, half):
    """(..., 4, 2) footprint corners."""
    c, s = np.cos(yaw)[..., None], np.sin(yaw)[..., None]
    hx = np.array([1, 1, -1, -1]) * half[..., 0:1]
    hy = np.array([1, -1, -1, 1]) * half[..., 1:2]
    return np.stack([centre[..., 0:1] + c * hx - s * hy, centre[..., 1:2] + s * hx + c * hy], -1)


def _overlap(a: np.ndarray, b: np.ndarray, margin: float) -> np.ndarray:
    """Separating-axis test of (..., 4, 2) rectangles, grown by ``margin``: (...,) bool."""
    axes = np.concatenate([a[..., 1:3, :] - a[..., 0:2, :], b[..., 1:3, :] - b[..., 0:2, :]], -2)
    axes = axes / np.linalg.norm(axes, axis=-1, keepdims=True)
    pa, pb = np.einsum("...ck,...ak->...ac", a, axes), np.einsum("...ck,...ak->...ac", b, axes)
    separated = (pa.min(-1) > pb.max(-1) + 2 * margin) | (pb.min(-1) > pa.max(-1) + 2 * margin)
    return ~separated.any(-1)


class _Placer:
    """Footprints already placed (per frame) and the non-overlap test for new ones."""

    def __init__(self, frames: int):
        self.frames = frames
        self.corners = np.zeros((0, frames, 4, 2))
        self.radius = np.zeros(0)

    def fits(self, xy: np.ndarray, yaw: np.ndarray, half, margin: float) -> bool:
        half = np.asarray(half, np.float64)
        corners = _corners(xy, yaw, np.broadcast_to(half, xy.shape))
        if len(self.radius):
            centres = self.corners.mean(-2)
            near = np.linalg.norm(centres - xy, axis=-1) < self.radius[:, None] + np.hypot(*half) + 2 * margin
            rows = np.flatnonzero(near.any(1))
            if (
                len(rows)
                and _overlap(self.corners[rows], np.broadcast_to(corners, (len(rows),) + corners.shape), margin).any()
            ):
                return False
        self.corners = np.concatenate([self.corners, corners[None]])
        self.radius = np.r_[self.radius, np.hypot(*half)]
        return True

    def add_static(self, x, y, yaw, half) -> None:
        xy = np.tile([x, y], (self.frames, 1)).astype(np.float64)
        corners = _corners(xy, np.full(self.frames, float(yaw)), np.broadcast_to(np.asarray(half, float), xy.shape))
        self.corners = np.concatenate([self.corners, corners[None]])
        self.radius = np.r_[self.radius, np.hypot(*half)]


def unicycle(x, y, yaw, speed, yaw_rate, times) -> tuple[np.ndarray, np.ndarray]:
    """(T, 2) positions and (T,) headings of constant speed and yaw rate motion at ``times`` (s)."""
    heading = yaw + yaw_rate * times
    if abs(yaw_rate) < 1e-9:
        dx, dy = speed * times * np.cos(yaw), speed * times * np.sin(yaw)
    else:
        dx = speed / yaw_rate * (np.sin(heading) - np.sin(yaw))
        dy = speed / yaw_rate * (np.cos(yaw) - np.cos(heading))
    return np.stack([x + dx, y + dy], -1), heading


def _speed(rng, low, high, fast_high=None, fast_probability=0.0) -> float:
    if fast_high is not None and rng.random() < fast_probability:
        return float(rng.uniform(high, fast_high))
    return float(rng.uniform(low, high))


class _Builder:
    def __init__(self, seed: int, frames: int, frequency_hz: float):
        self.rng = np.random.default_rng(seed)
        self.seed = seed
        self.times = np.arange(frames) / frequency_hz
        self.frames = frames
        self.placer = _Placer(frames)
        self.prims = []  # (kind, owner, local, size)
        self.owners = [(np.tile(np.eye(4), (frames, 1, 1)), 0, 0.0)]  # (poses, class, speed)

    def ground(self) -> Ground:
        rng = self.rng
        count = 3
        wavelength = rng.uniform(8.0, 40.0, count)
        direction = rng.uniform(0, np.pi, count)
        waves = np.stack([np.cos(direction), np.sin(direction)], -1) * (2 * np.pi / wavelength)[:, None]
        return Ground(
            slope=(float(rng.normal(0, 0.008)), float(rng.normal(0, 0.008))),
            offset=0.0,
            amplitudes=rng.uniform(0.005, 0.03, count),
            waves=waves,
            phases=rng.uniform(0, 2 * np.pi, count),
            kerb=float(rng.uniform(0.1, 0.2)),
            cross_x=float(rng.uniform(-25.0, 45.0)),
        )

    def pose(self, xy: np.ndarray, heading: np.ndarray) -> np.ndarray:
        """(T, 4, 4) world_from_owner standing on the ground at ``xy`` with ``heading``."""
        return _transform(self.g.orientation(heading), np.c_[xy, self.g.height(xy[:, 0], xy[:, 1])])

    def static(self, shapes, x, y, yaw=0.0, footprint=None):
        """World-standing structure (owner 0) placed at (x, y) with ``yaw``."""
        place = self.pose(np.array([[x, y]]), np.array([yaw]))[0]
        for kind, local, size in shapes:
            self.prims.append((kind, 0, place @ local, size))
        if footprint is not None:
            self.placer.add_static(x, y, yaw, footprint)

    def agent(self, cls, x, y, yaw, speed, yaw_rate, margin=0.15, shaped=None) -> bool:
        """Place an agent unless its footprint overlaps another at some frame; True if placed. ``shaped`` is an
        ``agent_shapes`` result to reuse."""
        shapes, half = agent_shapes(cls, self.rng) if shaped is None else shaped
        xy, heading = unicycle(x, y, yaw, speed, yaw_rate, self.times)
        if not self.placer.fits(xy, heading, half, margin):
            return False
        owner = len(self.owners)
        self.owners.append((self.pose(xy, heading), cls, speed))
        for kind, local, size in shapes:
            self.prims.append((kind, owner, local, size))
        return True


#: distance (m) from the ego at which ``_range_edge`` agents cross in or out: the default ``Lidar.max_range``
RANGE_EDGE = 75.0


def build_scene(seed: int, frames: int = 5, frequency_hz: float = 10.0, density: float = 1.0) -> Scene:
    """The world of one sequence, fully determined by ``seed`` (see the module docstring).

    ``density`` scales the number of moving agents. Timestamps start at 0 ns.
    """
    if frames < 2 or frequency_hz <= 0:
        raise ValueError(f"build_scene: need frames >= 2 and frequency_hz > 0, got {frames}, {frequency_hz}")
    b = _Builder(seed, frames, frequency_hz)
    rng = b.rng
    g = b.g = b.ground()

    # ego: a lane of the main road heading +x, 0-20 m/s, turning in a third of the sequences
    ego_speed = 0.0 if rng.random() < 0.1 else float(rng.uniform(0.0, 20.0))
    ego_rate = float(rng.choice([-1, 1]) * rng.uniform(0.1, 0.4)) if rng.random() < 0.35 else float(rng.normal(0, 0.02))
    ego_xy, ego_heading = unicycle(
        0.0, float(rng.choice([-1.75, -5.25])), float(rng.normal(0, 0.03)), ego_speed, ego_rate, b.times
    )
    ego_poses = b.pose(ego_xy, ego_heading)
    b.placer.fits(ego_xy, ego_heading, (2.45, 1.0), 0.0)

    _structures(b, g)
    _parked(b)
    _traffic(b, g, density)
    _range_edge(b, ego_xy)

    kinds, owners, locals_, sizes = zip(*b.prims)
    poses, classes, speeds = zip(*b.owners)
    return Scene(
        seed=seed,
        timestamps_ns=np.round(b.times * 1e9).astype(np.int64),
        ego_poses=ego_poses,
        ground=g,
        owner_poses=np.stack(poses),
        owner_instance=np.arange(len(poses), dtype=np.int32),
        owner_class=np.array(classes, np.int32),
        owner_speed=np.array(speeds, np.float64),
        kind=np.array(kinds, np.int8),
        owner=np.array(owners, np.int32),
        local=np.stack(locals_),
        size=np.array(sizes, np.float64),
    )


def _outside_cross(x0, x1, g: Ground, pad: float) -> bool:
    return x1 < g.cross_x - CROSS_HALF - pad or x0 > g.cross_x + CROSS_HALF + pad


def _structures(b: _Builder, g: Ground) -> None:
    """Buildings, poles, trees and bushes along both sides of the main road and the cross street."""
    rng = b.rng
    for side in (-1.0, 1.0):
        x = -90.0 + rng.uniform(0, 10)
        while x < 90.0:  # building row along the main road
            length, gap = rng.uniform(8, 28), rng.uniform(1, 10)
            if _outside_cross(x, x + length, g, SIDEWALK):
                depth, height = rng.uniform(8, 15), rng.uniform(4, 18)
                near = ROAD_HALF + SIDEWALK + rng.uniform(0.0, 2.5)
                y = side * (near + depth / 2)
                b.static([_box(length, depth, -0.5, height)], x + length / 2, y, footprint=(length / 2, depth / 2))
            x += length + gap
        for across in (-1.0, 1.0):  # buildings along the cross street
            y = side * (ROAD_HALF + SIDEWALK + rng.uniform(0, 4))
            while abs(y) < 90.0:
                length, depth, height = rng.uniform(8, 20), rng.uniform(8, 14), rng.uniform(4, 15)
                x = g.cross_x + across * (CROSS_HALF + SIDEWALK + rng.uniform(0, 2) + depth / 2)
                # corners overlapping the main-road rows are harmless: both are static
                b.static(
                    [_box(depth, length, -0.5, height)], x, y + side * length / 2, footprint=(depth / 2, length / 2)
                )
                y += side * (length + rng.uniform(1, 8))
        x = -80.0 + rng.uniform(0, 10)
        while x < 80.0:  # poles at the kerb
            if _outside_cross(x, x, g, 1.0):
                radius = rng.uniform(0.08, 0.18)
                b.static(
                    [_cylinder(radius, -0.2, rng.uniform(4, 9))],
                    x,
                    side * (ROAD_HALF + 0.6),
                    footprint=(radius, radius),
                )
            x += rng.uniform(10, 30)
        x = -80.0 + rng.uniform(0, 10)
        while x < 80.0:  # trees: trunk and canopy
            if _outside_cross(x, x, g, 2.5):
                top = rng.uniform(2.2, 3.2)
                rx, rz = rng.uniform(1.2, 2.4), rng.uniform(1.0, 2.0)
                canopy = _ellipsoid(rx, rx * rng.uniform(0.8, 1.0), rz, z=top + rz * 0.8)
                shapes = [_cylinder(0.15, -0.2, top + 0.5), canopy]
                b.static(shapes, x, side * (ROAD_HALF + rng.uniform(2.0, 3.0)), footprint=(0.2, 0.2))
            x += rng.uniform(7, 22)
        for _ in range(rng.integers(2, 6)):  # bush clusters in front of the walls
            x = rng.uniform(-60, 60)
            if _outside_cross(x - 2, x + 2, g, 0.0):
                y = side * (ROAD_HALF + SIDEWALK - 0.4)
                shapes = [
                    _ellipsoid(rng.uniform(0.4, 0.9), rng.uniform(0.3, 0.6), rng.uniform(0.3, 0.7), x=dx, z=0.3)
                    for dx in np.linspace(-1.2, 1.2, rng.integers(2, 4))
                ]
                b.static(shapes, x, y, footprint=(1.8, 0.6))


def _parked(b: _Builder) -> None:
    """Parked cars and vans in the parking lanes: static agents with their own instance ids."""
    rng = b.rng
    for _ in range(rng.integers(4, 11)):
        side = rng.choice([-1.0, 1.0])
        cls = OTHER_VEHICLE if rng.random() < 0.2 else CAR
        heading = (0.0 if side < 0 else np.pi) + rng.normal(0, 0.03)
        b.agent(cls, rng.uniform(-45, 50), side * PARKING + rng.normal(0, 0.15), heading, 0.0, 0.0, margin=0.3)


def _traffic(b: _Builder, g: Ground, density: float) -> None:
    """Moving vehicles, cyclists and pedestrians; close pairs, fast ones, turning ones."""
    rng = b.rng

    def lane_vehicle(cls, lane, x, speed=None, rate=None, shaped=None):
        heading = 0.0 if lane < 0 else np.pi
        speed = _speed(rng, 0.0, 15.0, 33.0, 0.2) if speed is None else speed
        rate = rng.normal(0, 0.02) if rate is None else rate
        return b.agent(cls, x, lane + rng.normal(0, 0.2), heading + rng.normal(0, 0.02), speed, rate, shaped=shaped)

    for _ in range(int(round(rng.integers(8, 15) * density))):  # main-road traffic
        cls = OTHER_VEHICLE if rng.random() < 0.25 else CAR
        lane_vehicle(cls, rng.choice(LANES), rng.uniform(-45, 55))
    for _ in range(int(round(rng.integers(1, 3) * density))):  # a platoon: the follower within 1 m
        lane, x, speed = rng.choice(LANES), rng.uniform(-35, 40), _speed(rng, 0.0, 12.0)
        shapes = agent_shapes(CAR, rng)
        if lane_vehicle(CAR, lane, x, speed, 0.0, shaped=shapes):
            follower = agent_shapes(CAR, rng)
            gap = shapes[1][0] + follower[1][0] + rng.uniform(0.5, 1.0)
            lane_vehicle(CAR, lane, x - gap * (1 if lane < 0 else -1), speed, 0.0, shaped=follower)
    for _ in range(int(round(rng.integers(1, 4) * density))):  # cross-street traffic, some turning
        lane = rng.choice(LANES)
        heading = np.pi / 2 if lane > 0 else -np.pi / 2
        turning = rng.random() < 0.4
        speed = _speed(rng, 2.0, 8.0) if turning else _speed(rng, 0.0, 14.0, 25.0, 0.2)
        rate = rng.choice([-1, 1]) * rng.uniform(0.2, 0.5) if turning else 0.0
        cls = OTHER_VEHICLE if rng.random() < 0.2 else CAR
        b.agent(cls, g.cross_x + lane, rng.uniform(-40, 40), heading, speed, rate)
    for _ in range(int(round(rng.integers(1, 4) * density))):  # cyclists at the lane edges
        side = rng.choice([-1.0, 1.0])
        b.agent(
            CYCLIST,
            rng.uniform(-35, 40),
            side * rng.uniform(6.6, 7.2),
            (0.0 if side < 0 else np.pi) + rng.normal(0, 0.05),
            _speed(rng, 2.0, 9.0),
            rng.normal(0, 0.05),
        )
    for _ in range(int(round(rng.integers(4, 11) * density))):  # pedestrians: along sidewalks, some crossing
        crossing = rng.random() < 0.25
        speed = 0.0 if rng.random() < 0.2 else _speed(rng, 0.6, 2.0)
        if crossing:
            x, y = g.cross_x + rng.uniform(-6, 6), rng.uniform(-9, 9)
            heading = rng.choice([-1, 1]) * np.pi / 2
        else:
            side = rng.choice([-1.0, 1.0])
            x, y = rng.uniform(-40, 45), side * (ROAD_HALF + rng.uniform(0.8, SIDEWALK - 0.8))
            heading = rng.choice([0.0, np.pi])
        heading += rng.normal(0, 0.1)
        rate = rng.normal(0, 0.2) if speed > 0 else 0.0
        if b.agent(PEDESTRIAN, x, y, heading, speed, rate, margin=0.1) and rng.random() < 0.5:
            offset = rng.uniform(0.55, 0.95)  # a companion walking side by side
            b.agent(
                PEDESTRIAN,
                x - offset * np.sin(heading),
                y + offset * np.cos(heading),
                heading,
                speed,
                rate,
                margin=0.05,
            )


def _range_edge(b: _Builder, ego_xy: np.ndarray) -> None:
    """One or two fast vehicles on the oncoming lanes that cross ``RANGE_EDGE`` metres from the ego during the
    sequence: one entering the sensor's range ahead, one leaving it behind (drawn last: earlier draws unchanged)."""
    rng = b.rng
    duration = b.times[-1]
    ego_speed = np.linalg.norm(ego_xy[-1] - ego_xy[0]) / duration
    for entering in (True, False)[: int(rng.integers(1, 3))]:
        speed = _speed(rng, 15.0, 33.0)
        lane = LANES[int(rng.integers(2, 4))]  # heading -x
        change = (speed + ego_speed) * duration  # the ego drives +x: the gap closes ahead, opens behind
        reach = RANGE_EDGE + change * rng.uniform(0.25, 0.75) * (1 if entering else -1)
        x = ego_xy[0, 0] + (reach if entering else -reach)
        cls = OTHER_VEHICLE if rng.random() < 0.3 else CAR
        b.agent(cls, x, lane + rng.normal(0, 0.2), np.pi + rng.normal(0, 0.01), speed, 0.0)
