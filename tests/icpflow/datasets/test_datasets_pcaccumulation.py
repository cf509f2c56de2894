"""PCAccumulation reader (Waymo, nuScenes): files written in PCAccumulation's layout from the synthetic world.

The layout and label encoding are those of PCAccumulation's writers (``dataset_toolbox/prep_nuscene_waymo_sf``):
int64 labels, float32 transforms, anchor = frame 0 = the latest scan, Waymo ``sem_labels`` per point (box type - 1:
0 vehicle, 1 pedestrian, 2 background or sign, 3 cyclist), nuScenes ``sem_labels`` the 16 lidarseg classes of the
anchor frame's points only.
"""

import pickle

import numpy as np
import pytest

from icpflow.core.frame_pair import FramePairError
from icpflow.datasets.pcaccumulation import PCAccumulationDataset

from helpers.pcaccumulation import FORMATS, WAYMO_CLASSES, reader, sample_arrays, world, write_dataset


@pytest.mark.parametrize("dataset", ["waymo", "nuscenes"])
def test_round_trip_gives_the_synthetic_pairs_into_the_anchor(tmp_path, dataset):
    write_dataset(tmp_path, dataset)
    data = reader(tmp_path, dataset)
    truth = world(dataset)
    frames, frequency = FORMATS[dataset]
    anchor = frames - 1
    assert len(data) == 1 and data.max_horizon == frames - 1 and data.sample_id(0) == "val/seg/000"
    for k in range(1, frames):
        pair, expected = data.pair(0, horizon=k), truth.pair(anchor - k, k)
        np.testing.assert_array_equal(pair.pc0, expected.pc0)
        np.testing.assert_array_equal(pair.pc1, expected.pc1)
        np.testing.assert_allclose(pair.ego1_from_ego0, expected.ego1_from_ego0, atol=1e-6)
        np.testing.assert_allclose(pair.flow, expected.flow, atol=1e-5)  # float32 transforms in the file: ~2e-6 m
        np.testing.assert_array_equal(pair.dynamic, expected.dynamic)
        assert expected.dynamic.sum() > 100  # moving agents are in the test
        np.testing.assert_array_equal(pair.instance > 0, expected.instance > 0)
        ids = np.unique(np.stack([pair.instance, expected.instance]), axis=1)
        assert len(np.unique(ids[0])) == len(np.unique(ids[1])) == ids.shape[1]  # a renumbering, one to one
        foreground = (expected.classes > 0).astype(np.int32)
        classes = WAYMO_CLASSES[expected.classes] if dataset == "waymo" else foreground
        np.testing.assert_array_equal(pair.classes, classes)
        assert pair.dt == pytest.approx(k / frequency)
        assert pair.ground0 is None and pair.sample_id == f"val/seg/000/{k}"


def test_waymo_classes_come_from_fb_labels_not_sem_labels(tmp_path):
    """Waymo boxes signs too: their points carry an instance but sem 2 and fb 0, so they stay background."""
    arrays, truth = sample_arrays(), world("waymo")
    rows = np.flatnonzero(arrays["time_indice"] == 1)  # frame c = 1 is scan 3
    sign = rows[(truth.classes[3] == 0) & ~truth.ground[3]][:50]
    arrays["inst_labels"][sign] = len(arrays["bbox_tsfm"])
    static = np.tile(np.eye(4, dtype=np.float32), (1, 5, 1, 1))
    write_dataset(tmp_path, inst_labels=arrays["inst_labels"], bbox_tsfm=np.concatenate([arrays["bbox_tsfm"], static]))
    pair, expected = reader(tmp_path).pair(0, horizon=1), truth.pair(3, 1)
    on_sign = np.isin(rows, sign)
    assert on_sign.sum() == 50 and (pair.instance[on_sign] > 0).all() and (pair.classes[on_sign] == 0).all()
    np.testing.assert_array_equal(pair.classes, WAYMO_CLASSES[expected.classes])
    np.testing.assert_allclose(pair.flow, expected.flow, atol=1e-5)


def test_sequence_gives_pairs_between_past_frames(tmp_path):
    write_dataset(tmp_path)
    sequence, dynamic = reader(tmp_path).sequence(0)
    assert len(sequence) == 5 and len(dynamic) == 5
    pair = sequence.pair(0, 2)  # the oldest frame (c = 4) to c = 2, neither the anchor
    np.testing.assert_allclose(pair.flow, world("waymo").pair(0, 2).flow, atol=1e-5)


def test_split_file_lists_samples(tmp_path):
    write_dataset(tmp_path)
    (tmp_path / "test_info.txt").write_text("/val/seg/000.npz\n\n")  # the reference's lines start with a slash
    dataset = PCAccumulationDataset(tmp_path, "test")
    assert dataset.files == [tmp_path / "val" / "seg" / "000.npz"]
    with pytest.raises(FramePairError, match="nope.txt: split file not found"):
        PCAccumulationDataset(tmp_path, "val", split_file=tmp_path / "nope.txt")


def test_no_samples_is_an_error(tmp_path):
    with pytest.raises(FramePairError, match="no samples"):
        PCAccumulationDataset(tmp_path, "val")


def test_unknown_sem_labels_encoding(tmp_path):
    with pytest.raises(ValueError, match="sem_labels must be one of waymo, nuscenes, got 'kitti'"):
        PCAccumulationDataset(tmp_path, "val", sem_labels="kitti")


def test_pickles(tmp_path):
    write_dataset(tmp_path)
    clone = pickle.loads(pickle.dumps(reader(tmp_path)))
    np.testing.assert_array_equal(clone.pair(0, 4).pc0, world("waymo").points[0])


def _error(root, dataset="waymo", frames=None) -> str:
    options = {} if frames is None else {"frames": frames}
    with pytest.raises(FramePairError) as error:
        PCAccumulationDataset(root, "val", sem_labels=dataset, **options).pair(0)
    assert "\n" not in str(error.value) and "000.npz" in str(error.value)
    return str(error.value)


def test_missing_key(tmp_path):
    write_dataset(tmp_path, bbox_tsfm=None)
    assert "missing key(s) bbox_tsfm" in _error(tmp_path)


def test_wrong_shape(tmp_path):
    write_dataset(tmp_path, raw_points=sample_arrays()["raw_points"][:, :2])
    assert "raw_points must be a numeric (N, 3) array" in _error(tmp_path)


def test_empty_scan(tmp_path):
    write_dataset(tmp_path, raw_points=np.zeros((0, 3), np.float32))
    assert "raw_points is an empty scan" in _error(tmp_path)


def test_frame_without_points(tmp_path):
    time = sample_arrays()["time_indice"]
    time[time == 2] = 1
    write_dataset(tmp_path, time_indice=time)
    assert "time_indice must cover frames 0..4, each non-empty" in _error(tmp_path)


def test_nan_rows(tmp_path):
    points = sample_arrays()["raw_points"]
    points[[0, 5, 9]] = np.nan
    write_dataset(tmp_path, raw_points=points)
    assert "raw_points has 3 rows with NaN" in _error(tmp_path)


def test_truncated_file(tmp_path):
    path = write_dataset(tmp_path)
    path.write_bytes(path.read_bytes()[:-200])
    assert "cannot read .npz" in _error(tmp_path)


def test_missing_pose(tmp_path):
    write_dataset(tmp_path, ego_motion_gt=sample_arrays()["ego_motion_gt"][:4])
    assert "ego_motion_gt must have shape (5, 4, 4) for 5 frames, got (4, 4, 4)" in _error(tmp_path)


def test_wrong_frame_count_for_the_dataset(tmp_path):
    write_dataset(tmp_path)
    assert "for 11 frames" in _error(tmp_path, frames=11)


def test_mismatched_label_length(tmp_path):
    write_dataset(tmp_path, sd_labels=np.zeros(10, np.int64))
    count = len(sample_arrays()["raw_points"])
    assert f"sd_labels must have shape ({count},) like raw_points, got (10,)" in _error(tmp_path)


def test_waymo_sem_labels_must_be_per_point(tmp_path):
    write_dataset(tmp_path, sem_labels=sample_arrays("nuscenes")["sem_labels"])
    assert "sem_labels must have shape" in _error(tmp_path)


def test_nuscenes_sem_labels_cover_the_anchor_only(tmp_path):
    write_dataset(tmp_path, "nuscenes")
    arrays = sample_arrays("nuscenes")
    assert len(arrays["sem_labels"]) == (arrays["time_indice"] == 0).sum() < len(arrays["raw_points"])
    assert reader(tmp_path, "nuscenes").pair(0).classes.max() == 1


def test_labels_that_are_not_binary(tmp_path):
    fb = sample_arrays()["fb_labels"]
    fb[7] = 2
    write_dataset(tmp_path, fb_labels=fb)
    assert "fb_labels must hold only 0 and 1" in _error(tmp_path)


def test_foreground_point_with_a_background_class(tmp_path):
    arrays = sample_arrays()
    sem = arrays["sem_labels"]
    sem[np.flatnonzero(arrays["fb_labels"])[:4]] = 2
    write_dataset(tmp_path, sem_labels=sem)
    assert "4 foreground points (fb_labels 1) have sem_labels outside 0 (vehicle), 1 (pedestrian), 3 (cyclist)" in (
        _error(tmp_path)
    )


def test_instance_without_motion(tmp_path):
    write_dataset(tmp_path, bbox_tsfm=sample_arrays()["bbox_tsfm"][:1])
    assert "inst_labels must lie in 0..0" in _error(tmp_path)


def test_non_rigid_object_motion(tmp_path):
    arrays = sample_arrays()
    k = int(arrays["inst_labels"][arrays["time_indice"] == 2].max())
    arrays["bbox_tsfm"][k, 2, 0, 0] = 2.0
    write_dataset(tmp_path, bbox_tsfm=arrays["bbox_tsfm"])
    assert f"bbox_tsfm[{k}, 2] is not rigid" in _error(tmp_path)


def test_extra_pickled_keys_are_never_loaded(tmp_path):
    write_dataset(tmp_path, scene_info=np.array({"segment": "abc"}, dtype=object))
    np.testing.assert_allclose(reader(tmp_path).pair(0).flow, world("waymo").pair(3, 1).flow, atol=1e-5)


def test_object_motion_of_frames_without_the_object_is_ignored(tmp_path):
    arrays = sample_arrays()
    k = int(arrays["inst_labels"][(arrays["time_indice"] == 2) & (arrays["sd_labels"] == 1)].max())
    keep = ~((arrays["time_indice"] == 2) & (arrays["inst_labels"] == k))  # the object is not seen in frame 2
    arrays["bbox_tsfm"][k, 2] = 0.0  # and its motion there is a zero placeholder
    per_point = ("raw_points", "time_indice", "sd_labels", "fb_labels", "inst_labels", "sem_labels")
    write_dataset(tmp_path, bbox_tsfm=arrays["bbox_tsfm"], **{key: arrays[key][keep] for key in per_point})
    dataset, truth = reader(tmp_path), world("waymo")
    for horizon in (1, 3, 4):
        np.testing.assert_allclose(dataset.pair(0, horizon).flow, truth.pair(4 - horizon, horizon).flow, atol=1e-5)
    pair = dataset.pair(0, horizon=2)
    assert k not in pair.instance
    np.testing.assert_allclose(pair.flow, truth.pair(2, 2).flow[keep[arrays["time_indice"] == 2]], atol=1e-5)
