"""The synthetic LiDAR world: determinism, exact ground truth, occlusion, sizes and the dataset reader."""

import pickle

import numpy as np
import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf

from icpflow.core.geometry import invert, transform_points
from icpflow.datasets.synthetic import AV2_META_CLASSES, CLASSES, Lidar, build_scene, scan, sequence
from icpflow.datasets.synthetic.lidar import _ground, cast, intersect, surface_distance
from icpflow.datasets.synthetic.reader import SyntheticDataset

from helpers.data import REPO

SMALL = Lidar(beams=16, azimuth_resolution_deg=1.0)  # fast; same world, fewer rays
EXACT = Lidar(beams=16, azimuth_resolution_deg=1.0, range_noise=0.0, dropout=0.0)
CONF = REPO / "conf" / "dataset" / "synthetic.yaml"


@pytest.fixture(scope="module")
def world():
    """A scene whose ego drives and turns, its noise-free small scans and sequence."""
    scene = build_scene(7, frames=5)
    scans = [scan(scene, t, SMALL, noise=False) for t in range(5)]
    return scene, scans, sequence(scene, SMALL, noise=False)


def test_same_seed_same_arrays_other_seed_differs():
    a, b = sequence(build_scene(11, 3), SMALL), sequence(build_scene(11, 3), SMALL)
    for t in range(3):
        assert np.array_equal(a.points[t], b.points[t]) and np.array_equal(a.instance[t], b.instance[t])
    assert np.array_equal(a.poses, b.poses)
    c = sequence(build_scene(12, 3), SMALL)
    assert len(c.points[0]) != len(a.points[0]) or not np.array_equal(c.points[0], a.points[0])


def test_splits_are_disjoint_and_reproducible():
    seeds = {
        split: {SyntheticDataset(split, num_sequences=50).sequence_seed(i) for i in range(50)}
        for split in ("train", "val", "test")
    }
    assert not (seeds["train"] & seeds["val"]) and not (seeds["val"] & seeds["test"])
    assert not (seeds["train"] & seeds["test"])
    with pytest.raises(ValueError, match="split"):
        SyntheticDataset("dev")


def test_scan_points_lie_on_the_primitive_they_hit(world):
    scene, scans, _ = world
    s = scans[0]
    poses = scene.primitive_poses(0)
    world_points = transform_points(scene.ego_poses[0], s.points.astype(np.float64))
    for p in np.unique(s.primitive[s.primitive > 0]):
        local = transform_points(invert(poses[p - 1]), world_points[s.primitive == p])
        assert surface_distance(scene.kind[p - 1], scene.size[p - 1], local).max() < 1e-4


def test_static_points_flow_is_ego_flow(world):
    scene, _, seq = world
    pair = seq.pair(0, 1)
    static_instances = np.flatnonzero(scene.owner_speed == 0)  # owner 0 (world) and parked agents
    static = np.isin(pair.instance, scene.owner_instance[static_instances])
    assert static.sum() > 100 and (pair.instance[static] > 0).any()
    assert np.abs(pair.flow[static] - pair.ego_flow()[static]).max() < 1e-5
    assert not pair.dynamic[static].any()
    assert np.linalg.norm(pair.ego1_from_ego0[:3, 3]) > 0.2  # the ego moves in this scene


def test_moving_points_moved_by_flow_lie_on_the_object_at_t1(world):
    scene, scans, seq = world
    pair, s = seq.pair(0, 1), scans[0]
    assert np.array_equal(pair.pc0, s.points)
    moving = scene.owner_speed[scene.owner[np.maximum(s.primitive, 1) - 1]] > 0
    moving &= s.primitive > 0
    assert moving.sum() > 50
    moved = transform_points(pair.pose1, (pair.pc0 + pair.flow).astype(np.float64))  # world, t + dt
    poses1 = scene.primitive_poses(1)
    for p in np.unique(s.primitive[moving]):
        local = transform_points(invert(poses1[p - 1]), moved[s.primitive == p])
        assert surface_distance(scene.kind[p - 1], scene.size[p - 1], local).max() < 1e-4


def test_object_flow_is_its_rigid_motion_and_dynamic_is_speed(world):
    scene, _, seq = world
    pair = seq.pair(0, 1)
    objects = scene.object_poses()
    checked = 0
    for inst in np.unique(pair.instance[pair.instance > 0]):
        mask = pair.instance == inst
        motion = invert(pair.pose1) @ objects[inst][1] @ invert(objects[inst][0]) @ pair.pose0
        expected = transform_points(motion, pair.pc0[mask].astype(np.float64)) - pair.pc0[mask]
        assert np.abs(pair.flow[mask] - expected).max() < 1e-5
        speed = scene.owner_speed[inst]
        if speed >= 1.0 or speed == 0.0:
            assert np.all(pair.dynamic[mask] == (speed > 0))
            checked += 1
    assert checked >= 5
    residual_speed = np.linalg.norm(pair.residual_flow(), axis=1) / pair.dt
    decided = np.abs(residual_speed - 0.5) > 1e-3
    assert np.array_equal(pair.dynamic[decided], residual_speed[decided] > 0.5)


def test_long_horizon_flow_composes_single_steps(world):
    scene, _, seq = world
    pair = seq.pair(0, 4)
    objects = scene.object_poses()
    for inst in np.unique(pair.instance):
        mask = pair.instance == inst
        step = np.eye(4)
        for t in range(4):  # ego_{t+1} <- ego_t for this instance, chained
            obj = objects[inst][t + 1] @ invert(objects[inst][t]) if inst > 0 else np.eye(4)
            step = invert(scene.ego_poses[t + 1]) @ obj @ scene.ego_poses[t] @ step
        expected = transform_points(step, pair.pc0[mask].astype(np.float64)) - pair.pc0[mask]
        assert np.abs(pair.flow[mask] - expected).max() < 1e-4
    assert pair.dt == pytest.approx(0.4)


def test_no_point_behind_a_nearer_hit(world):
    """Brute force over every primitive and the ground for every returned ray: the culling loses nothing."""
    scene = world[0]
    s = cast(scene, 2, EXACT, np.random.default_rng(9))  # a spin phase between columns, exact ranges
    assert 0 < s.azimuth_offset < 1
    directions = EXACT.directions(s.azimuth_offset)[s.beam, s.column]
    sensor = scene.ego_poses[2].copy()
    sensor[:3, 3] += EXACT.height * sensor[:3, 2]
    poses = invert(sensor) @ scene.primitive_poses(2)
    nearest = _ground(scene, sensor[:3, 3], directions @ sensor[:3, :3].T, np.full(len(s.range), np.inf), EXACT)
    hit = np.zeros(len(s.range), np.int64)
    for p in range(len(scene.kind)):
        rotation = poses[p, :3, :3]
        t = intersect(scene.kind[p], scene.size[p], -rotation.T @ poses[p, :3, 3], directions @ rotation)
        hit[t < nearest] = p + 1
        nearest = np.minimum(nearest, t)
    assert np.abs(nearest - s.range).max() < 1e-4  # ground roots by bisection: brackets differ here
    assert np.array_equal(hit, s.primitive)


def test_ground_mask_marks_height_field_hits(world):
    scene, scans, seq = world
    s, pair = scans[0], seq.pair(0, 1)
    assert np.array_equal(pair.ground0, s.primitive == 0) and 0.2 < pair.ground0.mean() < 0.9
    assert not pair.instance[pair.ground0].any() and not pair.classes[pair.ground0].any()
    directions = SMALL.directions()[s.beam, s.column]
    sensor = np.array([0.0, 0.0, SMALL.height])
    g = scene.ground
    for offset, above in ((-1e-3, True), (1e-3, False)):  # just before the hit above, just after at or below
        p = transform_points(scene.ego_poses[0], sensor + (s.range + offset)[:, None] * directions)
        side = p[:, 2] - g.height(p[:, 0], p[:, 1]) > 0
        assert np.all(side[pair.ground0] == above)


def test_range_noise_moves_points_along_their_rays():
    scene = build_scene(3, 2)
    clean = cast(scene, 0, EXACT, np.random.default_rng(5))  # same spin phase as the noisy scan, no noise
    noisy = cast(scene, 0, SMALL, np.random.default_rng(5))
    assert 0 < noisy.azimuth_offset == clean.azimuth_offset < 1
    assert scan(scene, 0, SMALL).azimuth_offset != scan(scene, 1, SMALL).azimuth_offset
    ray_clean = clean.beam * 10000 + clean.column
    ray_noisy = noisy.beam * 10000 + noisy.column
    common, i, j = np.intersect1d(ray_clean, ray_noisy, return_indices=True)
    assert len(common) == len(noisy.range) and 0.95 < len(noisy.range) / len(clean.range) < 0.99  # 3 % dropout
    assert 0.017 < np.std(noisy.range[j] - clean.range[i]) < 0.023

    def unit(points):
        rays = points - [0.0, 0.0, SMALL.height]
        return rays / np.linalg.norm(rays, axis=1, keepdims=True)

    assert np.abs(unit(noisy.points[j]) - unit(clean.points[i])).max() < 1e-5


def test_default_sizes_and_schema():
    data = SyntheticDataset("val", num_sequences=1, frames_per_sequence=2)
    pair = data.pair(0)
    assert 70_000 < len(pair.pc0) < 150_000 and 70_000 < len(pair.pc1) < 150_000
    assert pair.pc0.dtype == pair.flow.dtype == np.float32
    assert pair.classes.dtype == pair.instance.dtype == np.int32
    assert pair.ground0.dtype == pair.dynamic.dtype == np.bool_ and pair.pose0.dtype == np.float64
    assert set(np.unique(pair.classes)) <= set(CLASSES) and pair.dynamic.any()
    half = scan(build_scene(data.sequence_seed(0), 2), 0, Lidar(beams=32))
    assert 0.35 < len(half.points) / len(pair.pc0) < 0.65


def test_class_table_maps_onto_av2_meta_classes():
    assert set(AV2_META_CLASSES) == set(CLASSES)
    assert set(AV2_META_CLASSES.values()) == {"BACKGROUND", "CAR", "OTHER_VEHICLES", "PEDESTRIAN", "WHEELED_VRU"}


def test_scenes_have_the_asked_for_variety():
    scenes = [build_scene(seed, 5) for seed in range(12)]
    speeds = np.concatenate([s.owner_speed for s in scenes])
    assert speeds.max() <= 33.0 and (speeds > 20).sum() >= 3 and ((speeds > 0) & (speeds < 15)).mean() > 0.5
    ego_speed = [np.linalg.norm(s.ego_poses[1, :3, 3] - s.ego_poses[0, :3, 3]) * 10 for s in scenes]
    assert max(ego_speed) <= 20.0 + 1e-6
    for s in scenes:
        moving = np.flatnonzero(s.owner_speed > 0)
        assert len(moving) >= 10 and set(s.owner_class[moving]) >= {1, 3}
        start = np.linalg.norm(s.owner_poses[moving, 0, :2, 3] - s.ego_poses[0, :2, 3], axis=1)
        assert (start[start < 60] < 40).mean() > 0.6  # most traffic near the ego (beyond 60 m: range-edge agents)
        assert 0.1 <= s.ground.kerb <= 0.2  # a kerb step off the road
        static = s.owner == 0
        assert (s.kind[static] == 2).any() and (s.kind[static] == 1).any()  # canopies and bushes; poles and trunks
    classes = np.concatenate([s.owner_class for s in scenes])
    assert set(classes) == {0, 1, 2, 3, 4}
    lengths = [
        2 * (np.abs(s.local[s.owner == o, 0, 3]) + s.size[s.owner == o, 0]).max()  # footprint length
        for s in scenes
        for o in np.flatnonzero(s.owner_class == 2)
    ]
    assert 10.0 <= max(lengths) <= 12.0  # buses up to 12 m


def test_dataset_indexing_lazy_and_picklable():
    data = SyntheticDataset("test", num_sequences=2, frames_per_sequence=3, beams=16, azimuth_resolution_deg=1.0)
    assert len(data) == 4 and data.max_horizon == 1
    assert data.sample_id(3) == "synthetic-test-2000001-16b/000001+1" and data._cached is None
    pair = data.pair(3)
    assert pair.sample_id == data.sample_id(3) and pair.dt == pytest.approx(0.1)
    longer = SyntheticDataset(
        "test", num_sequences=2, frames_per_sequence=3, beams=16, azimuth_resolution_deg=1.0, max_horizon=2
    )
    assert len(longer) == 2 and longer.pair(1, horizon=2).sample_id == "synthetic-test-2000001-16b/000000+2"
    copy = pickle.loads(pickle.dumps(data))
    assert copy._cached is None and np.array_equal(copy.pair(3).pc0, pair.pc0)
    with pytest.raises(IndexError):
        data.pair(4)
    with pytest.raises(IndexError):
        data.pair(0, horizon=2)
    assert SyntheticDataset("val", 1, 3, frequency_hz=20.0, beams=16, azimuth_resolution_deg=1.0).pair(0).dt == 0.05


def test_hydra_config_instantiates():
    config = OmegaConf.create({"split": "val", "dataset": OmegaConf.load(CONF)})
    assert config.dataset.name == "synthetic" and config.dataset.preset == "waymo" and config.dataset.root is None
    data = instantiate(config.dataset.reader)
    assert isinstance(data, SyntheticDataset) and data.split == "val" and len(data) <= 8
    # the reader takes the YAML's settings, not its own defaults: change them in the config and see them arrive
    config.dataset.reader.beams, config.dataset.reader.frequency_hz = 32, 20.0
    changed = instantiate(config.dataset.reader)
    assert (changed.lidar.beams, changed.frequency_hz) == (32, 20.0)
    assert changed.pair(0).dt == 0.05 and changed.sample_id(0).endswith("-32b/000000+1")


def test_some_agents_enter_or_leave_the_sensor_range():
    lidar = Lidar(beams=32, azimuth_resolution_deg=0.5)  # default 75 m range
    crossings = 0
    for seed in range(4):
        seq = sequence(build_scene(seed, 5), lidar)
        seen = [set(np.unique(i[i > 0]).tolist()) for i in seq.instance]
        crossings += len((seen[0] ^ seen[-1]) - set.intersection(*seen[1:-1]))
        for t in range(5):  # nothing is ever seen beyond the range
            assert np.linalg.norm(seq.points[t] - [0, 0, lidar.height], axis=1).max() <= lidar.max_range + 0.1
    assert crossings >= 3
