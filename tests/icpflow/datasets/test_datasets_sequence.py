"""`dataset=sequence`: ordered scans in .bin/.npy/.ply/.pcd with an optional poses file."""

import pickle
from pathlib import Path

import numpy as np
import pytest

from icpflow.core.frame_pair import FramePairError
from icpflow.core.geometry import invert, make_transform, transform_points
from icpflow.core.open3d_loader import load_open3d
from icpflow.datasets.scan_folder import ScanSequenceDataset

from helpers.data import needs_shared, shared

SCANS = shared("kitti_hdl64_scans")
needs_scans = needs_shared("kitti_hdl64_scans", what="the real KITTI HDL-64 scans")
RNG = np.random.default_rng(5)
CLOUDS = [RNG.uniform(-30, 30, (200 + 10 * i, 3)).astype(np.float32) for i in range(4)]
POSES = np.stack([make_transform(yaw=0.01 * i, translation=(0.8 * i, 0.0, 0.0)) for i in range(4)])


def write_scans(folder: Path, suffix: str, names=None) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    names = names or [str(i) for i in range(len(CLOUDS))]
    paths = []
    for name, cloud in zip(names, CLOUDS):
        path = folder / f"{name}{suffix}"
        if suffix == ".bin":
            np.c_[cloud, np.ones(len(cloud), np.float32)].tofile(path)
        elif suffix == ".npy":
            np.save(path, cloud)
        else:
            o3d = load_open3d()
            points = o3d.utility.Vector3dVector(cloud.astype(float))
            o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(points))
        paths.append(path)
    return paths


@pytest.mark.parametrize("suffix", [".bin", ".npy", ".ply", ".pcd"])
def test_each_format_reads_back(tmp_path, suffix):
    write_scans(tmp_path, suffix)
    dataset = ScanSequenceDataset(tmp_path, sensor_height=0.0)  # random clouds: no ground to lift onto
    assert len(dataset) == 3 and dataset.sample_id(2) == "2"
    pair = dataset.pair(2)
    np.testing.assert_allclose(pair.pc0, CLOUDS[2], atol=1e-5)
    np.testing.assert_allclose(pair.pc1, CLOUDS[3], atol=1e-5)
    assert pair.ego1_from_ego0 is None and pair.dt == pytest.approx(0.1)


def test_natural_order_and_horizon(tmp_path):
    write_scans(tmp_path, ".npy", names=["scan_9", "scan_10", "scan_11", "scan_100"])
    dataset = ScanSequenceDataset(tmp_path, frequency_hz=20.0, max_horizon=2, sensor_height=0.0)
    assert [p.name for p in dataset.scans] == ["scan_9.npy", "scan_10.npy", "scan_11.npy", "scan_100.npy"]
    assert len(dataset) == 2
    pair = dataset.pair(1, horizon=2)
    np.testing.assert_array_equal(pair.pc1, CLOUDS[3])
    assert pair.dt == pytest.approx(0.1) and pair.timestamp1_ns == 150_000_000


def test_kitti_style_poses_file_is_found(tmp_path):
    write_scans(tmp_path, ".bin")
    np.savetxt(tmp_path / "poses.txt", POSES[:, :3].reshape(4, 12))
    pair = ScanSequenceDataset(tmp_path).pair(1)
    np.testing.assert_allclose(pair.ego1_from_ego0, invert(POSES[2]) @ POSES[1], atol=1e-9)


@pytest.mark.parametrize("name", ["poses16.txt", "poses.npy"])
def test_other_pose_formats(tmp_path, name):
    write_scans(tmp_path / "scans", ".npy")
    path = tmp_path / name
    np.save(path, POSES) if name.endswith(".npy") else np.savetxt(path, POSES.reshape(4, 16))
    dataset = pickle.loads(pickle.dumps(ScanSequenceDataset(tmp_path / "scans", poses_file=path, sensor_height=0)))
    np.testing.assert_allclose(dataset.pair(0).pose1, POSES[1], atol=1e-12)


@needs_scans
def test_real_scans_without_poses():
    dataset = ScanSequenceDataset(SCANS)
    assert len(dataset) == 5
    pair = dataset.pair(0)
    assert pair.ego1_from_ego0 is None and len(pair.pc0) == 124668


def street(sensor_height: float, seed: int) -> np.ndarray:
    """(N, 3) float32 scan of a flat road ``sensor_height`` m below the sensor, with walls and boxes on it."""
    rng = np.random.default_rng(seed)
    radius, angle = rng.uniform(3, 40, 20000), rng.uniform(-np.pi, np.pi, 20000)
    road = np.c_[radius * np.cos(angle), radius * np.sin(angle), rng.normal(0, 0.02, 20000)]
    wall = np.c_[rng.uniform(-40, 40, 8000), np.full(8000, 12.0), rng.uniform(0, 6, 8000)]
    boxes = np.c_[rng.uniform(5, 9, 3000), rng.uniform(-3, -1, 3000), rng.uniform(0, 1.6, 3000)]
    return (np.vstack([road, wall, boxes]) - [0, 0, sensor_height]).astype(np.float32)


@pytest.mark.parametrize("height", [0.6, 1.73, 3.2])
def test_auto_sensor_height_lifts_any_mounting_onto_the_ground(tmp_path, height):
    """sensor_height=auto (the default) finds the ground below the sensor of the first scan and lifts every scan
    by it, whatever the mounting height: the road then lies at z = 0 and the poses are the lifted frame's."""
    for index in range(3):
        np.save(tmp_path / f"{index}.npy", street(height, index))
    np.savetxt(tmp_path / "poses.txt", POSES[:3, :3].reshape(3, 12))
    dataset = ScanSequenceDataset(tmp_path)
    assert dataset.lift() == pytest.approx(height, abs=0.05)
    assert ScanSequenceDataset(tmp_path, sensor_height="auto").lift() == dataset.lift()
    pair = dataset.pair(1)
    road = np.abs(street(height, 1)[:, 2] + height) < 0.1
    assert abs(np.median(pair.pc0[road, 2])) < 0.05
    np.testing.assert_allclose(pair.pc0[:, :2], street(height, 1)[:, :2])
    # a point fixed in the world keeps its world position through the lifted poses
    point = np.array([[4.0, -2.0, 0.3]])
    world0 = transform_points(pair.pose0, point)
    np.testing.assert_allclose(world0, transform_points(POSES[1], point - [0, 0, dataset.lift()]), atol=1e-9)


def test_scans_already_in_the_height_frame_stay(tmp_path):
    """A ground found within 0.5 m of z = 0 (an ego frame on the ground) means no lift: the scans are read as is."""
    for index in range(2):
        np.save(tmp_path / f"{index}.npy", street(-0.3, index))  # the road 0.3 m above the origin
    dataset = ScanSequenceDataset(tmp_path)
    assert dataset.lift() == 0.0
    np.testing.assert_array_equal(dataset.pair(0).pc0, street(-0.3, 0))


@needs_scans
def test_real_scans_are_lifted_by_their_estimated_height():
    """The HDL-64E sits about 1.73 m above the road: auto finds that within 0.1 m; a given height is used as is."""
    assert ScanSequenceDataset(SCANS).lift() == pytest.approx(1.73, abs=0.1)
    pair = ScanSequenceDataset(SCANS, sensor_height=1.73).pair(0)
    raw = np.fromfile(SCANS / "000000.bin", np.float32).reshape(-1, 4)[:, :3]
    np.testing.assert_allclose(pair.pc0, raw + np.float32([0, 0, 1.73]), atol=1e-6)


# -- malformed -----------------------------------------------------------------------------------------------------
def _error(folder, index=0, **options) -> str:
    with pytest.raises(FramePairError) as error:
        ScanSequenceDataset(folder, **options).pair(index)
    assert "\n" not in str(error.value)
    return str(error.value)


def test_mixed_formats(tmp_path):
    write_scans(tmp_path, ".npy")
    write_scans(tmp_path, ".bin")
    with pytest.raises(FramePairError, match=r"need scans of one format, found .bin, .npy"):
        ScanSequenceDataset(tmp_path)


def test_too_few_scans(tmp_path):
    write_scans(tmp_path, ".npy", names=["only"])
    with pytest.raises(FramePairError, match="1 scans make no pair"):
        ScanSequenceDataset(tmp_path)


def test_truncated_bin(tmp_path):
    path = write_scans(tmp_path, ".bin")[0]
    path.write_bytes(path.read_bytes()[:-3])
    assert "0.bin: size 3197 bytes is not a whole number of 4-float32 rows" in _error(tmp_path)


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".npy"])
def test_truncated_files(tmp_path, suffix):
    path = write_scans(tmp_path, suffix)[1]
    path.write_bytes(path.read_bytes()[: len(path.read_bytes()) // 2])
    message = _error(tmp_path, index=1)
    assert f"1{suffix}:" in message and ("truncated" in message or "no points read" in message)


def test_empty_scan(tmp_path):
    write_scans(tmp_path, ".npy")
    np.save(tmp_path / "0.npy", np.zeros((0, 3), np.float32))
    assert "0.npy: scan is an empty scan" in _error(tmp_path)


def test_wrong_shape(tmp_path):
    write_scans(tmp_path, ".npy")
    np.save(tmp_path / "1.npy", np.zeros((10, 2), np.float32))
    assert "1.npy: scan must be a numeric (N, 3) array" in _error(tmp_path)


def test_nan_rows(tmp_path):
    write_scans(tmp_path, ".npy")
    cloud = CLOUDS[1].copy()
    cloud[[1, 2]] = np.nan
    np.save(tmp_path / "1.npy", cloud)
    assert "1.npy: scan has 2 rows with NaN" in _error(tmp_path)


def test_missing_pose(tmp_path):
    write_scans(tmp_path, ".npy")
    np.savetxt(tmp_path / "poses.txt", POSES[:3, :3].reshape(3, 12))
    assert "poses.txt: 3 poses for 4 scans" in _error(tmp_path)


def test_bad_pose_line(tmp_path):
    write_scans(tmp_path, ".npy")
    (tmp_path / "poses.txt").write_text("1 2 3 4 5\n")
    assert "poses.txt: line 1 has 5 values, expected 12 (3 x 4) or 16 (4 x 4)" in _error(tmp_path)


def test_pose_array_of_wrong_shape(tmp_path):
    write_scans(tmp_path / "scans", ".npy")
    np.save(tmp_path / "poses.npy", np.zeros((4, 3, 4)))
    assert "poses.npy: poses must have shape (T, 4, 4), got float64 (4, 3, 4)" in _error(
        tmp_path / "scans", poses_file=tmp_path / "poses.npy"
    )
