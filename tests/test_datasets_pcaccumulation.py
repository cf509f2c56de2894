"""PCAccumulation reader (Waymo, nuScenes): files written in the real layout from a hand-built rigid world."""

import pickle

import numpy as np
import pytest

from icpflow.datasets.pcaccumulation import PCAccumulationDataset
from icpflow.frames import FramePairError
from icpflow.geometry import invert, make_transform, transform_points

RNG = np.random.default_rng(7)
STATIC_WORLD = RNG.uniform((-30, -30, -1.8), (30, 30, 2.0), (300, 3))
OBJECT_BODY = RNG.uniform((-2.0, -1.0, -0.8), (2.0, 1.0, 0.8), (80, 3))


def ego_pose(t):
    return make_transform(yaw=0.02 * t, translation=(1.0 * t, 0.1 * t, 0.0))


def object_pose(t):
    return make_transform(yaw=0.05 * t, translation=(5.0 + 0.8 * t, 3.0, 0.0))


def sample_arrays(frames: int) -> dict:
    """A sample in PCAccumulation's layout: scan t (oldest first) is frame c = F - 1 - t; anchor = the last scan.

    Every frame sees the same physical points in the same order (static first, then the object), so the exact
    flow of frame c maps its points row by row onto the anchor's.
    """
    anchor = frames - 1
    anchor_from_world = invert(ego_pose(anchor))
    points, time, inst = [], [], []
    for c in range(frames):
        t = anchor - c
        world = np.concatenate([STATIC_WORLD, transform_points(object_pose(t), OBJECT_BODY)])
        points.append(transform_points(invert(ego_pose(t)), world))
        time.append(np.full(len(world), c))
        inst.append(np.r_[np.zeros(len(STATIC_WORLD)), np.ones(len(OBJECT_BODY))])
    inst = np.concatenate(inst).astype(np.int64)
    boxes = np.tile(np.eye(4), (2, frames, 1, 1))
    for c in range(frames):
        motion_in_world = object_pose(anchor) @ invert(object_pose(anchor - c))
        boxes[1, c] = anchor_from_world @ motion_in_world @ invert(anchor_from_world)
    return {
        "raw_points": np.concatenate(points).astype(np.float32),
        "time_indice": np.concatenate(time).astype(np.float32),
        "sd_labels": inst.astype(np.float32),
        "fb_labels": inst.astype(np.float32),
        "inst_labels": inst,
        "sem_labels": inst * 3,
        "ego_motion_gt": np.stack([anchor_from_world @ ego_pose(anchor - c) for c in range(frames)]).astype(np.float32),
        "bbox_tsfm": boxes.astype(np.float32),
    }


def write_dataset(root, frames=5, **changes):
    (root / "val" / "seg").mkdir(parents=True, exist_ok=True)
    arrays = {**sample_arrays(frames), **changes}
    for key in [k for k, v in arrays.items() if v is None]:
        del arrays[key]
    np.savez(root / "val" / "seg" / "000.npz", **arrays)
    return root / "val" / "seg" / "000.npz"


@pytest.mark.parametrize("frames, frequency", [(5, 10.0), (11, 20.0)])
def test_round_trip_flow_maps_every_frame_onto_the_anchor(tmp_path, frames, frequency):
    write_dataset(tmp_path, frames)
    dataset = PCAccumulationDataset(tmp_path, "val", frames=frames, frequency_hz=frequency)
    assert len(dataset) == 1 and dataset.max_horizon == frames - 1
    assert dataset.sample_id(0) == "val/seg/000"
    anchor = frames - 1
    n_object = len(OBJECT_BODY)
    for k in range(1, frames):
        pair = dataset.pair(0, horizon=k)
        np.testing.assert_allclose(pair.pc0 + pair.flow, pair.pc1, atol=2e-4)
        expected_ego = invert(ego_pose(anchor)) @ ego_pose(anchor - k)
        np.testing.assert_allclose(pair.ego1_from_ego0, expected_ego, atol=1e-5)
        np.testing.assert_allclose(pair.residual_flow()[:-n_object], 0.0, atol=2e-4)  # static rows
        assert pair.dynamic.sum() == n_object and pair.dynamic[-n_object:].all()
        np.testing.assert_array_equal(pair.instance, np.r_[np.zeros(300), np.ones(n_object)].astype(np.int32))
        np.testing.assert_array_equal(pair.classes, 3 * pair.instance)
        assert pair.dt == pytest.approx(k / frequency)
        assert pair.ground0 is None and pair.sample_id == f"val/seg/000/{k}"


def test_sequence_gives_pairs_between_past_frames(tmp_path):
    write_dataset(tmp_path)
    sequence, dynamic = PCAccumulationDataset(tmp_path, "val").sequence(0)
    assert len(sequence) == 5 and len(dynamic) == 5
    pair = sequence.pair(0, 2)  # the oldest frame (c = 4) to c = 2, neither the anchor
    np.testing.assert_allclose(pair.pc0 + pair.flow, pair.pc1, atol=2e-4)


def test_split_file_lists_samples(tmp_path):
    write_dataset(tmp_path)
    (tmp_path / "test_info.txt").write_text("val/seg/000.npz\n\n")
    dataset = PCAccumulationDataset(tmp_path, "test")
    assert dataset.files == [tmp_path / "val" / "seg" / "000.npz"]
    with pytest.raises(FramePairError, match="nope.txt: split file not found"):
        PCAccumulationDataset(tmp_path, "val", split_file=tmp_path / "nope.txt")


def test_no_samples_is_an_error(tmp_path):
    with pytest.raises(FramePairError, match="no samples"):
        PCAccumulationDataset(tmp_path, "val")


def test_pickles(tmp_path):
    write_dataset(tmp_path)
    clone = pickle.loads(pickle.dumps(PCAccumulationDataset(tmp_path, "val")))
    assert clone.pair(0, 4).pc0.shape == (380, 3)


def _error(root, frames=5) -> str:
    with pytest.raises(FramePairError) as error:
        PCAccumulationDataset(root, "val", frames=frames).pair(0)
    assert "\n" not in str(error.value) and "000.npz" in str(error.value)
    return str(error.value)


def test_missing_key(tmp_path):
    write_dataset(tmp_path, bbox_tsfm=None)
    assert "missing key(s) bbox_tsfm" in _error(tmp_path)


def test_wrong_shape(tmp_path):
    arrays = sample_arrays(5)
    write_dataset(tmp_path, raw_points=arrays["raw_points"][:, :2])
    assert "raw_points must be a numeric (N, 3) array" in _error(tmp_path)


def test_empty_scan(tmp_path):
    write_dataset(tmp_path, raw_points=np.zeros((0, 3), np.float32))
    assert "raw_points is an empty scan" in _error(tmp_path)


def test_frame_without_points(tmp_path):
    arrays = sample_arrays(5)
    time = arrays["time_indice"].copy()
    time[time == 2] = 1
    write_dataset(tmp_path, time_indice=time)
    assert "time_indice must cover frames 0..4, each non-empty" in _error(tmp_path)


def test_nan_rows(tmp_path):
    points = sample_arrays(5)["raw_points"]
    points[[0, 5, 9]] = np.nan
    write_dataset(tmp_path, raw_points=points)
    assert "raw_points has 3 rows with NaN" in _error(tmp_path)


def test_truncated_file(tmp_path):
    path = write_dataset(tmp_path)
    path.write_bytes(path.read_bytes()[:-200])
    assert "cannot read .npz" in _error(tmp_path)


def test_missing_pose(tmp_path):
    write_dataset(tmp_path, ego_motion_gt=sample_arrays(5)["ego_motion_gt"][:4])
    assert "ego_motion_gt must have shape (5, 4, 4) for 5 frames, got (4, 4, 4)" in _error(tmp_path)


def test_wrong_frame_count_for_the_dataset(tmp_path):
    write_dataset(tmp_path, frames=5)
    assert "for 11 frames" in _error(tmp_path, frames=11)


def test_mismatched_label_length(tmp_path):
    write_dataset(tmp_path, sd_labels=np.zeros(10))
    assert "sd_labels must have shape (1900,) like raw_points, got (10,)" in _error(tmp_path)


def test_instance_without_motion(tmp_path):
    write_dataset(tmp_path, bbox_tsfm=sample_arrays(5)["bbox_tsfm"][:1])
    assert "inst_labels must lie in 0..0" in _error(tmp_path)


def test_non_rigid_object_motion(tmp_path):
    boxes = sample_arrays(5)["bbox_tsfm"]
    boxes[1, 2, 0, 0] = 2.0
    write_dataset(tmp_path, bbox_tsfm=boxes)
    assert "bbox_tsfm[1, 2] is not rigid" in _error(tmp_path)


def test_extra_pickled_keys_are_never_loaded(tmp_path):
    write_dataset(tmp_path, scene_info=np.array({"segment": "abc"}, dtype=object))
    pair = PCAccumulationDataset(tmp_path, "val").pair(0)
    np.testing.assert_allclose(pair.pc0 + pair.flow, pair.pc1, atol=2e-4)


def test_object_motion_of_frames_without_the_object_is_ignored(tmp_path):
    arrays = sample_arrays(5)
    keep = ~((arrays["time_indice"] == 2) & (arrays["inst_labels"] == 1))  # the object is not seen in frame 2
    boxes = arrays["bbox_tsfm"]
    boxes[1, 2] = 0.0  # and its motion there is a zero placeholder
    write_dataset(tmp_path, bbox_tsfm=boxes, **{key: arrays[key][keep] for key in ("raw_points", "time_indice",
                  "sd_labels", "fb_labels", "inst_labels", "sem_labels")})  # fmt: skip
    dataset = PCAccumulationDataset(tmp_path, "val")
    for k in (1, 3, 4):
        pair = dataset.pair(0, horizon=k)
        np.testing.assert_allclose(pair.pc0 + pair.flow, pair.pc1, atol=2e-4)
    assert dataset.pair(0, horizon=2).instance.sum() == 0
