"""KITTI odometry reader: the real sequence-01 frames laid out as the official download, and the bare HDL-64 scans."""

import pickle

import numpy as np
import pytest
from scipy.spatial import cKDTree

from icpflow.core.frame_pair import FramePairError
from icpflow.core.geometry import make_transform, relative_transform, transform_points
from icpflow.datasets.kitti import SENSOR_HEIGHT, KittiOdometryDataset, read_calib_tr
from icpflow.scans.preprocess import estimate_ground_height, lift_pose, lift_transform

from helpers.data import needs_shared, shared

SEQ01 = shared("kitti_odometry_seq01")
SCANS = shared("kitti_hdl64_scans")
needs_seq01 = needs_shared("kitti_odometry_seq01", what="the real KITTI sequence 01 frames")


@pytest.fixture
def kitti_root(tmp_path):
    """sequences/01/{velodyne/*.bin, calib.txt, times.txt} and poses/01.txt built from the shared real files."""
    velodyne = tmp_path / "sequences" / "01" / "velodyne"
    velodyne.mkdir(parents=True)
    for frame in range(3):
        points = np.load(SEQ01 / f"kitti_01_points_{frame:06d}.npy")
        scan = np.concatenate([points, np.zeros((len(points), 1), np.float32)], axis=1)
        scan.astype(np.float32).tofile(velodyne / f"{frame:06d}.bin")
    timed = np.loadtxt(SEQ01 / "01_first5_with_time.txt")
    (tmp_path / "poses").mkdir()
    np.savetxt(tmp_path / "poses" / "01.txt", timed[:, 1:])
    np.savetxt(tmp_path / "sequences" / "01" / "times.txt", timed[:, 0])
    calib = (SEQ01 / "calib_seq00-02_Tr.txt").read_text()
    (tmp_path / "sequences" / "01" / "calib.txt").write_text("P0: " + " ".join(["0"] * 12) + "\n" + calib)
    return tmp_path


@needs_seq01
def test_velodyne_poses_match_the_reference(kitti_root):
    """sensor_height=0 keeps KITTI's velodyne frame: points and poses as the reference has them."""
    dataset = KittiOdometryDataset(kitti_root, split="train", max_horizon=2, sensor_height=0.0)
    assert len(dataset) == 1 and dataset.sample_id(0) == "01/000000"
    reference = np.load(SEQ01 / "kitti_odom_seq01_frames000-002_with_gt_poses.npz")
    for horizon in (1, 2):
        pair = dataset.pair(0, horizon=horizon)
        np.testing.assert_allclose(pair.pose0, reference["velo_poses_world"][0], atol=1e-6)
        np.testing.assert_allclose(pair.pose1, reference["velo_poses_world"][horizon], atol=1e-6)
        np.testing.assert_array_equal(pair.pc1, reference[f"points{horizon}"])
        assert pair.dt == pytest.approx(reference["timestamps_s"][horizon])
        assert pair.flow is None and pair.sample_id == "01/000000" + ("" if horizon == 1 else "+2")


@needs_seq01
def test_reader_lifts_the_velodyne_frame_onto_the_ground(kitti_root):
    """By default the scans come in the height frame (README conventions): lifted by the 1.73 m mounting height,
    so the road (SemanticKITTI class 9) lies near z = 0, and the poses and ego motion are those of that frame."""
    pair = KittiOdometryDataset(kitti_root, split="train").pair(0)
    reference = np.load(SEQ01 / "kitti_odom_seq01_frames000-002_with_gt_poses.npz")
    road = np.load(SEQ01 / "kitti_01_labels_000000.npy").reshape(-1) == 9
    assert abs(np.median(reference["points0"][road, 2]) + SENSOR_HEIGHT) < 0.15  # the velodyne frame: about -1.73
    assert abs(np.median(pair.pc0[road, 2])) < 0.15 and abs(estimate_ground_height(pair.pc0)) < 0.15
    np.testing.assert_allclose(pair.pc1, reference["points1"] + np.float32([0, 0, SENSOR_HEIGHT]), atol=1e-6)
    np.testing.assert_allclose(pair.pose1, lift_pose(reference["velo_poses_world"][1], SENSOR_HEIGHT), atol=1e-6)
    velodyne_ego = relative_transform(*reference["velo_poses_world"][:2])
    np.testing.assert_allclose(pair.ego1_from_ego0, lift_transform(velodyne_ego, SENSOR_HEIGHT), atol=1e-6)
    # the same static point in both frames: the ego motion maps the lifted scan exactly as the velodyne one
    point = reference["points0"][:5].astype(np.float64)
    lifted = transform_points(pair.ego1_from_ego0, point + [0, 0, SENSOR_HEIGHT])
    np.testing.assert_allclose(lifted - [0, 0, SENSOR_HEIGHT], transform_points(velodyne_ego, point), atol=1e-6)


@needs_seq01
def test_ego_motion_aligns_the_static_scene(kitti_root):
    pair = KittiOdometryDataset(kitti_root, sequences=["1"]).pair(0)
    labels = np.load(SEQ01 / "kitti_01_labels_000000.npy").reshape(-1)
    structure = np.isin(labels, [14, 15, 18, 19])  # fence, vegetation, pole, sign: static, not ground
    tree = cKDTree(pair.pc1)

    def median_gap(transform):
        return np.median(tree.query(transform_points(transform, pair.pc0[structure]))[0])

    aligned = median_gap(pair.ego1_from_ego0)
    assert aligned < 0.11  # the scan-line spacing; the README's ICP check agreed with these poses to 1.1 cm
    assert aligned < 0.5 * median_gap(np.eye(4))
    assert aligned < median_gap(make_transform(translation=(0.1, 0.0, 0.0)) @ pair.ego1_from_ego0)
    assert aligned < median_gap(make_transform(yaw=np.radians(0.5)) @ pair.ego1_from_ego0)


@needs_seq01
def test_split_selects_sequences(kitti_root):
    with pytest.raises(FramePairError, match="no velodyne scans for sequences 08; found 01"):
        KittiOdometryDataset(kitti_root, split="val")
    with pytest.raises(ValueError, match="unknown split"):
        KittiOdometryDataset(kitti_root, split="everything")


@needs_shared("kitti_hdl64_scans", what="the real KITTI HDL-64 scans")
def test_bare_scan_folder_has_no_poses():
    dataset = KittiOdometryDataset(SCANS)
    assert len(dataset) == 5 and dataset.sample_id(4) == "kitti_hdl64_scans/000004"
    pair = pickle.loads(pickle.dumps(dataset)).pair(4)
    assert pair.ego1_from_ego0 is None and pair.pose0 is None
    assert pair.pc0.dtype == np.float32 and 100_000 < len(pair.pc0) < 150_000
    raw = np.fromfile(SCANS / "000005.bin", np.float32).reshape(-1, 4)
    np.testing.assert_array_equal(pair.pc1, raw[:, :3] + np.float32([0, 0, SENSOR_HEIGHT]))
    assert pair.dt == pytest.approx(0.1)


def test_calib_tr_is_read(tmp_path):
    (tmp_path / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\nTr: 0 -1 0 1 0 0 -1 2 1 0 0 3\n")
    expected = np.array([[0, -1, 0, 1], [0, 0, -1, 2], [1, 0, 0, 3], [0, 0, 0, 1]], float)
    np.testing.assert_array_equal(read_calib_tr(tmp_path / "calib.txt"), expected)


# -- malformed files (small synthetic scans in the official layout) ----------------------------------------------
@pytest.fixture
def small_root(tmp_path):
    velodyne = tmp_path / "sequences" / "00" / "velodyne"
    velodyne.mkdir(parents=True)
    rng = np.random.default_rng(0)
    for frame in range(3):
        rng.uniform(-10, 10, (100, 4)).astype(np.float32).tofile(velodyne / f"{frame:06d}.bin")
    (tmp_path / "poses").mkdir()
    np.savetxt(tmp_path / "poses" / "00.txt", np.tile(np.eye(4)[:3].reshape(1, 12), (3, 1)))
    (tmp_path / "sequences" / "00" / "calib.txt").write_text("Tr: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    return tmp_path


def _error(root, index=0) -> str:
    with pytest.raises(FramePairError) as error:
        KittiOdometryDataset(root, "train").pair(index)
    assert "\n" not in str(error.value)
    return str(error.value)


def test_small_layout_reads(small_root):
    pair = KittiOdometryDataset(small_root, "train").pair(1)
    np.testing.assert_array_equal(pair.ego1_from_ego0, np.eye(4))
    assert pair.pc0.shape == (100, 3) and pair.dt == pytest.approx(0.1)


def test_truncated_scan(small_root):
    path = small_root / "sequences" / "00" / "velodyne" / "000001.bin"
    path.write_bytes(path.read_bytes()[:-6])
    assert "000001.bin: size 1594 bytes is not a whole number of 4-float32 rows" in _error(small_root)


def test_empty_scan(small_root):
    (small_root / "sequences" / "00" / "velodyne" / "000000.bin").write_bytes(b"")
    assert "000000.bin: scan is an empty scan" in _error(small_root)


def test_nan_rows(small_root):
    path = small_root / "sequences" / "00" / "velodyne" / "000001.bin"
    scan = np.fromfile(path, np.float32).reshape(-1, 4)
    scan[10, 2] = np.nan
    scan.tofile(path)
    assert "000001.bin: scan has 1 rows with NaN" in _error(small_root)


def test_missing_pose(small_root):
    np.savetxt(small_root / "poses" / "00.txt", np.eye(4)[:3].reshape(1, 12))
    assert "00.txt: 1 poses for 3 scans" in _error(small_root)


def test_pose_line_with_wrong_shape(small_root):
    (small_root / "poses" / "00.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0\n1 0 0 0 0 1 0 0 0 0 1 0\n")
    assert "00.txt: line 2 has 3 values, expected 12" in _error(small_root)


def test_missing_calib_tr(small_root):
    (small_root / "sequences" / "00" / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    assert "calib.txt: no 'Tr:' line" in _error(small_root)


def test_non_rigid_pose(small_root):
    poses = np.tile(np.eye(4)[:3].reshape(1, 12), (3, 1))
    poses[1, 0] = 3.0
    np.savetxt(small_root / "poses" / "00.txt", poses)
    assert "pose1 is not rigid" in _error(small_root)


def test_missing_calib_file_where_poses_exist(small_root):
    (small_root / "sequences" / "00" / "calib.txt").unlink()
    message = _error(small_root)
    assert message.endswith("sequences/00/calib.txt: file not found (needed to turn camera poses into velodyne poses)")


def test_scans_without_poses_need_no_calib(small_root):
    (small_root / "sequences" / "00" / "calib.txt").unlink()
    (small_root / "poses" / "00.txt").unlink()
    assert KittiOdometryDataset(small_root, "train").pair(0).ego1_from_ego0 is None


@pytest.mark.parametrize(
    "content, message",
    [
        ("0.0\n0.1\n", "times.txt: 2 times for 3 scans"),
        ("0.0\n0.1\nsoon\n", "times.txt: not a column of seconds"),
        ("0.0\n0.0\n0.2\n", "times.txt: times of scans 0 and 1 not increasing"),
    ],
)
def test_bad_times(small_root, content, message):
    (small_root / "sequences" / "00" / "times.txt").write_text(content)
    assert message in _error(small_root)


def test_times_give_dt(small_root):
    (small_root / "sequences" / "00" / "times.txt").write_text("0.0\n0.1037\n0.2075\n")
    pair = KittiOdometryDataset(small_root, "train").pair(1)
    assert pair.dt == pytest.approx(0.1038) and pair.timestamp1_ns == 207_500_000
