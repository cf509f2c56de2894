"""ZeroFlow-dump reader: NaN-padded files written in the dump's layout from a hand-built rigid scene."""

import pickle

import numpy as np
import pytest

from icpflow.core.frame_pair import FramePairError
from icpflow.datasets.zeroflow import ZeroFlowAV2Dataset

from helpers.zeroflow import LOG, dump_arrays, write_dump


@pytest.mark.parametrize("index_kind", ["indices", "mask"])
def test_round_trip(tmp_path, index_kind):
    write_dump(tmp_path, **dump_arrays(index_kind=index_kind))
    dataset = ZeroFlowAV2Dataset(tmp_path, "val")
    assert len(dataset) == 1 and dataset.sample_id(0) == f"{LOG}/000007"
    pair = dataset.pair(0)
    assert pair.pc0.shape == (250, 3) and pair.pc1.shape == (250, 3)
    np.testing.assert_array_equal(pair.ego1_from_ego0, np.eye(4))
    np.testing.assert_allclose(pair.pc0 + pair.flow, pair.pc1, atol=1e-5)
    np.testing.assert_array_equal(pair.flow, pair.residual_flow())
    np.testing.assert_array_equal(pair.classes, np.r_[np.zeros(200), np.full(50, 19)].astype(np.int32))
    np.testing.assert_array_equal(pair.dynamic, np.r_[np.zeros(200, bool), np.ones(50, bool)])
    assert not pair.ground0.any() and not pair.ground1.any() and pair.flow_valid.all()
    assert pair.dt == 0.1 and pair.log_id == LOG


def test_ground_masks_of_the_dump_are_used(tmp_path):
    ground1 = np.zeros(270, bool)
    ground1[:10] = True
    write_dump(tmp_path, ground1=ground1, ground2=np.zeros(280, bool))
    pair = ZeroFlowAV2Dataset(tmp_path, "val").pair(0)
    assert pair.ground0.sum() == 10 and pair.ground0[:10].all() and not pair.ground1.any()


def test_pickles_and_rejects_other_horizons(tmp_path):
    write_dump(tmp_path)
    dataset = pickle.loads(pickle.dumps(ZeroFlowAV2Dataset(tmp_path, "val")))
    assert dataset.pair(0).pc0.shape == (250, 3)
    with pytest.raises(IndexError):
        dataset.pair(0, horizon=2)


def test_no_files(tmp_path):
    with pytest.raises(FramePairError, match="val_zero_flow: no <log_id>/<index>.npz files"):
        ZeroFlowAV2Dataset(tmp_path, "val")


def _error(root) -> str:
    with pytest.raises(FramePairError) as error:
        ZeroFlowAV2Dataset(root, "val").pair(0)
    assert "\n" not in str(error.value) and "000007.npz" in str(error.value)
    return str(error.value)


def test_missing_key(tmp_path):
    write_dump(tmp_path, gt_flow_0_1=None)
    assert "missing key(s) gt_flow_0_1" in _error(tmp_path)


def test_wrong_shape(tmp_path):
    write_dump(tmp_path, pc2=np.zeros((10, 4), np.float32))
    assert "pc2 must have shape (M, 3), got (10, 4)" in _error(tmp_path)


def test_mismatched_flow_length(tmp_path):
    write_dump(tmp_path, gt_flow_0_1=np.zeros((100, 3), np.float32))
    assert "gt_flow_0_1 must have the shape of pc1 (270, 3), got (100, 3)" in _error(tmp_path)


def test_empty_scan(tmp_path):
    write_dump(tmp_path, pc1_flows_valid_idx=np.zeros(0, np.int64))
    assert "pc1 has no valid points" in _error(tmp_path)


@pytest.mark.parametrize("index_kind", ["indices", "mask"])
def test_padding_marked_valid_is_an_error(tmp_path, index_kind):
    valid = np.arange(255) if index_kind == "indices" else np.r_[np.ones(255, bool), np.zeros(15, bool)]
    write_dump(tmp_path, pc1_flows_valid_idx=valid)  # 5 NaN padding rows among the valid ones
    assert "pc1 has 5 NaN or Inf rows among its 255 valid rows" in _error(tmp_path)


def test_nan_point_inside_the_scan(tmp_path):
    pc2 = dump_arrays()["pc2"]
    pc2[17, 1] = np.nan
    write_dump(tmp_path, pc2=pc2)
    assert "pc2 has 1 NaN or Inf rows among its 250 valid rows" in _error(tmp_path)


def test_nan_flow_on_a_real_point(tmp_path):
    flow = dump_arrays()["gt_flow_0_1"]
    flow[4] = np.nan
    write_dump(tmp_path, gt_flow_0_1=flow)
    assert "gt_flow_0_1 has NaN or Inf at 1 valid points" in _error(tmp_path)


def test_valid_index_out_of_range(tmp_path):
    write_dump(tmp_path, pc1_flows_valid_idx=np.array([0, 1, 999]))
    assert "pc1_flows_valid_idx has indices outside 0..269" in _error(tmp_path)


def test_truncated_file(tmp_path):
    path = write_dump(tmp_path)
    path.write_bytes(path.read_bytes()[:500])
    assert "cannot read .npz" in _error(tmp_path)


def test_classes_out_of_range(tmp_path):
    classes = dump_arrays()["pc1_classes"]
    classes[0] = 40
    write_dump(tmp_path, pc1_classes=classes)
    assert "pc1_classes must lie in -1..29" in _error(tmp_path)
