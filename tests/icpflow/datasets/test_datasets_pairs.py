"""`dataset=pairs`: a directory of .npz pair files written by the tests."""

import pickle

import numpy as np
import pytest

from icpflow.core.frame_pair import FramePairError
from icpflow.core.geometry import ego_flow, make_transform
from icpflow.datasets.pairs import NpzPairsDataset

RNG = np.random.default_rng(11)
PC0 = RNG.uniform(-20, 20, (120, 3))
PC1 = RNG.uniform(-20, 20, (130, 3))
EGO = make_transform(yaw=0.03, translation=(1.2, 0.1, 0.0))


def write(folder, name="pair_000", **arrays):
    folder.mkdir(parents=True, exist_ok=True)
    arrays = {"pc0": PC0, "pc1": PC1, **arrays}
    np.savez(folder / f"{name}.npz", **{key: value for key, value in arrays.items() if value is not None})
    return folder / f"{name}.npz"


def test_minimal_pair(tmp_path):
    write(tmp_path)
    dataset = NpzPairsDataset(tmp_path)
    assert len(dataset) == 1 and dataset.sample_id(0) == "pair_000"
    pair = dataset.pair(0)
    assert pair.pc0.dtype == np.float32 and pair.pc1.shape == (130, 3)
    np.testing.assert_array_equal(pair.pc0, PC0.astype(np.float32))
    assert pair.ego1_from_ego0 is None and pair.flow is None and pair.dt == 0.1


def test_everything_is_cast_to_the_schema(tmp_path):
    flow = ego_flow(PC0, EGO).astype(np.float64)
    write(
        tmp_path,
        ego1_from_ego0=EGO.astype(np.float32),
        ground0=(PC0[:, 2] < -15).astype(np.uint8),
        ground1=PC1[:, 2] < -15,
        flow=flow,
        classes=np.arange(120, dtype=np.int64) % 3,
        instance=np.zeros(120, np.int16),
        dynamic=np.zeros(120, bool),
        flow_valid=np.ones(120, bool),
        dt=np.float64(0.05),
    )
    pair = NpzPairsDataset(tmp_path).pair(0)
    np.testing.assert_allclose(pair.ego1_from_ego0, EGO, atol=1e-6)
    assert pair.ego1_from_ego0.dtype == np.float64 and pair.flow.dtype == np.float32
    assert pair.ground0.dtype == np.bool_ and pair.ground0.sum() == (PC0[:, 2] < -15).sum()
    assert pair.classes.dtype == np.int32 and pair.classes[:4].tolist() == [0, 1, 2, 0]
    np.testing.assert_allclose(pair.residual_flow(), 0.0, atol=1e-4)
    assert pair.dt == 0.05


def test_poses_give_the_ego_motion(tmp_path):
    pose0 = make_transform(yaw=0.5, translation=(10.0, 5.0, 0.0))
    write(tmp_path, pose0=pose0, pose1=pose0 @ np.linalg.inv(EGO))
    pair = NpzPairsDataset(tmp_path).pair(0)
    np.testing.assert_allclose(pair.ego1_from_ego0, EGO, atol=1e-9)


def test_split_folder_and_sorting(tmp_path):
    write(tmp_path / "val", "b")
    write(tmp_path / "val", "a")
    write(tmp_path, "top")
    dataset = pickle.loads(pickle.dumps(NpzPairsDataset(tmp_path, split="val")))
    assert [dataset.sample_id(i) for i in range(len(dataset))] == ["a", "b"]
    assert NpzPairsDataset(tmp_path, split="train").files == [tmp_path / "top.npz"]  # no train/: the root itself


def test_no_files(tmp_path):
    with pytest.raises(FramePairError, match="no .npz pair files"):
        NpzPairsDataset(tmp_path)


def _error(folder) -> str:
    with pytest.raises(FramePairError) as error:
        NpzPairsDataset(folder).pair(0)
    assert "\n" not in str(error.value) and "pair_000.npz" in str(error.value)
    return str(error.value)


def test_missing_key(tmp_path):
    write(tmp_path, pc1=None)
    assert "missing key(s) pc1" in _error(tmp_path)


def test_unknown_keys_are_never_read_and_said_once(tmp_path):
    """Only the keys read matter: an extra key (a misspelt field, or an object array that would need unpickling) is
    named in one warning and ignored, never loaded."""
    write(tmp_path, scene_flow=np.zeros((120, 3)), meta=np.array([{"a": 1}], dtype=object))
    dataset = NpzPairsDataset(tmp_path)
    with pytest.warns(UserWarning, match=r"pair_000.npz: key\(s\) meta, scene_flow are no pair field and are ignored"):
        pair = dataset.pair(0)
    assert pair.pc0.shape == PC0.shape and pair.flow is None


def test_wrong_shape(tmp_path):
    write(tmp_path, pc0=np.zeros((120, 2)))
    assert "pc0 must be a numeric (N, 3) array, got float64 (120, 2)" in _error(tmp_path)
    write(tmp_path, pc0=PC0.T.copy())
    assert "pc0 has shape (3, 120): a transposed scan?" in _error(tmp_path)


def test_extra_columns_are_dropped_like_every_reader(tmp_path):
    write(tmp_path, pc0=np.hstack([PC0, np.ones((120, 1))]))
    np.testing.assert_array_equal(NpzPairsDataset(tmp_path).pair(0).pc0, PC0.astype(np.float32))


def test_empty_scan(tmp_path):
    write(tmp_path, pc1=np.zeros((0, 3)))
    assert "pc1 is an empty scan" in _error(tmp_path)


def test_nan_rows(tmp_path):
    pc0 = PC0.copy()
    pc0[7, 1] = np.nan
    write(tmp_path, pc0=pc0)
    assert "pc0 has 1 rows with NaN or Inf (of 120)" in _error(tmp_path)


def test_mismatched_flow_length(tmp_path):
    write(tmp_path, flow=np.zeros((119, 3)))
    assert "flow must have shape (120, 3), got (119, 3)" in _error(tmp_path)


def test_truncated_file(tmp_path):
    path = write(tmp_path)
    path.write_bytes(path.read_bytes()[:300])
    assert "cannot read .npz" in _error(tmp_path)


def test_non_rigid_ego_motion(tmp_path):
    write(tmp_path, ego1_from_ego0=np.diag([2.0, 1.0, 1.0, 1.0]))
    assert "ego1_from_ego0 is not rigid" in _error(tmp_path)


def test_half_a_pose(tmp_path):
    write(tmp_path, pose0=np.eye(4))
    assert "pose0 and pose1 must be given together" in _error(tmp_path)


def test_float_labels_are_refused(tmp_path):
    write(tmp_path, classes=np.full(120, 1.5))
    assert "classes must hold integers or booleans, got float64" in _error(tmp_path)


def test_ground_truth_without_the_ego_motion_is_refused_by_the_metrics_in_one_line(tmp_path):
    """Issue 45.6: the ego motion is optional for labelling (the teacher estimates it) but the metrics split points
    by their motion beyond the ego's: a pair with ground truth and no ego motion was an IndexError in eval.py."""
    from icpflow.datasets.synthetic.reader import SyntheticDataset
    from icpflow.evaluation.metrics import PairTruth

    pair = SyntheticDataset(split="test", num_sequences=1, frames_per_sequence=2, beams=32)[0]
    (tmp_path / "pairs").mkdir()
    np.savez(tmp_path / "pairs" / "0.npz", pc0=pair.pc0, pc1=pair.pc1, flow=pair.flow, classes=pair.classes)
    loaded = NpzPairsDataset(tmp_path / "pairs")[0]
    with pytest.raises(ValueError, match=r"0.npz: has ground-truth flow but no ego motion \(ego1_from_ego0, or pose0"):
        PairTruth.of_pair(loaded)
