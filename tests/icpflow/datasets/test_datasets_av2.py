"""AV2 reader on the real log in ../shared/data/av2 (official layout) and on damaged copies of it."""

import pickle
import shutil

import numpy as np
import pandas as pd
import pytest

from icpflow.core.frame_pair import FramePairError
from icpflow.core.geometry import ego_flow

from helpers.data import needs_shared, shared

pytest.importorskip("av2", reason="the av2 package is an optional dependency (pip install icpflow[av2])")
from icpflow.datasets.av2 import AV2Dataset  # noqa: E402

LOG = "7fab2350-7eaf-3b7e-a39d-6937a4c1bede"
ROOT = shared("av2")
STAMP0, STAMP1 = 315966265259836000, 315966265360032000
pytestmark = needs_shared("av2", "sensor", "val", LOG, what="the real Argoverse 2 log")


@pytest.fixture(scope="module")
def real_pair():
    return AV2Dataset(ROOT, "val").pair(0)


@pytest.fixture(scope="module")
def labels():
    return pd.read_feather(ROOT / "sensor" / "val" / LOG / "flow_labels.feather")


def test_listing_and_ids():
    dataset = AV2Dataset(ROOT, "val")
    assert len(dataset) == 1
    assert dataset.sample_id(0) == f"{LOG}/{STAMP0}"
    assert dataset.metadata()["logs"] == 1
    assert len(AV2Dataset(ROOT, "val", max_horizon=2)) == 0  # two sweeps make no pair 2 apart


def test_points_poses_and_times(real_pair):
    raw = pd.read_feather(ROOT / "sensor" / "val" / LOG / "sensors" / "lidar" / f"{STAMP0}.feather")
    assert real_pair.pc0.dtype == np.float32 and real_pair.pc0.shape == (99229, 3)
    assert real_pair.pc1.shape == (99466, 3)
    np.testing.assert_array_equal(real_pair.pc0, raw[["x", "y", "z"]].to_numpy(np.float32))
    ego = np.load(ROOT / "sensor" / "val" / LOG / "ego_motion.npz")["ego_motion"][0]
    np.testing.assert_allclose(real_pair.ego1_from_ego0, ego, atol=1e-3)
    assert (real_pair.timestamp0_ns, real_pair.timestamp1_ns) == (STAMP0, STAMP1)
    assert real_pair.dt == pytest.approx(0.100196)
    assert real_pair.log_id == LOG
    # per-point capture times: offset_ns in seconds, 0 to ~0.1 s after the sweep's timestamp
    assert real_pair.time0.dtype == np.float32 and real_pair.time0.shape == (99229,)
    np.testing.assert_allclose(real_pair.time0, raw["offset_ns"].to_numpy() * 1e-9, rtol=1e-6)
    assert real_pair.time1.shape == (99466,)
    assert 0.0 < real_pair.time1.min() < 0.01 and 0.09 < real_pair.time1.max() < 0.11


def test_flow_matches_official_labels(real_pair, labels):
    official = labels[["flow_tx_m", "flow_ty_m", "flow_tz_m"]].to_numpy()
    error = np.linalg.norm(real_pair.flow - official, axis=1)
    assert np.mean(error < 1e-3) >= 0.99
    # the official labels compose the city poses in float32 (about 8e-4 m of ego-motion error here); with their
    # own ego motion (ego_motion.npz) removed from both, the residual flows agree to micrometres
    official_ego = np.load(ROOT / "sensor" / "val" / LOG / "ego_motion.npz")["ego_motion"][0]
    official_residual = official - ego_flow(real_pair.pc0, official_ego)
    residual_error = np.linalg.norm(real_pair.residual_flow() - official_residual, axis=1)
    assert np.median(residual_error) < 1e-5


def test_classes_and_dynamic_equal_official_labels(real_pair, labels):
    np.testing.assert_array_equal(real_pair.classes, labels["classes"].to_numpy().astype(np.int32))
    np.testing.assert_array_equal(real_pair.dynamic, labels["dynamic"].to_numpy())
    assert real_pair.dynamic.sum() == 2037
    assert real_pair.classes.dtype == np.int32 and real_pair.classes.max() > 0


def test_static_points_have_ego_flow(real_pair):
    static = ~real_pair.dynamic & (real_pair.classes == 0)
    assert static.sum() > 80_000  # 89,832 of the 99,229 points: the check below is not over an empty selection
    np.testing.assert_allclose(real_pair.flow[static], real_pair.ego_flow()[static], atol=1e-5)


def test_ground_agrees_with_official_mask(real_pair, labels):
    agreement = np.mean(real_pair.ground0 == labels["is_ground_0"].to_numpy())
    assert agreement >= 0.9999
    assert 0.1 < real_pair.ground1.mean() < 0.3


def test_ground_threshold_is_an_option(labels):
    wider = AV2Dataset(ROOT, "val", ground_threshold=0.4, with_flow=False).pair(0)
    official = labels["is_ground_0"].to_numpy()
    assert wider.flow is None
    assert official.sum() > 15_000  # 17,374 official ground points (18,694 within 0.4 m): a check of some points
    assert wider.ground0[official].all()  # a wider band only adds ground points
    assert wider.ground0.sum() > official.sum()


def test_pickles_without_its_cache():
    dataset = AV2Dataset(ROOT, "val")
    dataset.pair(0)
    clone = pickle.loads(pickle.dumps(dataset))
    assert clone._cache == {}
    np.testing.assert_array_equal(clone.pair(0).pc1, dataset.pair(0).pc1)


# -- damaged copies ---------------------------------------------------------------------------------------------
@pytest.fixture
def log_copy(tmp_path):
    log_dir = tmp_path / "sensor" / "val" / LOG
    shutil.copytree(ROOT / "sensor" / "val" / LOG, log_dir)
    return tmp_path, log_dir


def _read_error(root) -> str:
    with pytest.raises(FramePairError) as error:
        AV2Dataset(root, "val").pair(0)
    message = str(error.value)
    assert "\n" not in message
    return message


def _sweep(log_dir, stamp=STAMP0):
    return log_dir / "sensors" / "lidar" / f"{stamp}.feather"


def test_missing_split_directory(tmp_path):
    with pytest.raises(FramePairError, match="sensor/val"):
        AV2Dataset(tmp_path, "val")


def test_missing_column(log_copy):
    root, log_dir = log_copy
    pd.read_feather(_sweep(log_dir)).drop(columns="z").to_feather(_sweep(log_dir))
    assert f"{STAMP0}.feather: missing column(s) z" in _read_error(root)


def test_empty_sweep(log_copy):
    root, log_dir = log_copy
    pd.read_feather(_sweep(log_dir)).iloc[:0].to_feather(_sweep(log_dir))
    assert "empty scan" in _read_error(root)


def test_nan_rows_in_a_sweep(log_copy):
    root, log_dir = log_copy
    frame = pd.read_feather(_sweep(log_dir))
    frame.loc[[3, 7], "y"] = np.nan
    frame.to_feather(_sweep(log_dir))
    assert f"{STAMP0}.feather: x, y, z has 2 rows with NaN" in _read_error(root)


def test_truncated_sweep(log_copy):
    root, log_dir = log_copy
    data = _sweep(log_dir, STAMP1).read_bytes()
    _sweep(log_dir, STAMP1).write_bytes(data[: len(data) // 2])
    message = _read_error(root)
    assert f"{STAMP1}.feather: cannot read feather" in message


def test_sweep_without_offsets_has_no_times(log_copy):
    root, log_dir = log_copy
    pd.read_feather(_sweep(log_dir, STAMP1)).drop(columns="offset_ns").to_feather(_sweep(log_dir, STAMP1))
    pair = AV2Dataset(root, "val").pair(0)
    assert pair.time0 is not None and pair.time1 is None


def test_non_integer_offsets(log_copy):
    root, log_dir = log_copy
    frame = pd.read_feather(_sweep(log_dir))
    frame["offset_ns"] = frame["offset_ns"].astype(np.float64)
    frame.to_feather(_sweep(log_dir))
    assert f"{STAMP0}.feather: offset_ns must hold integer nanoseconds" in _read_error(root)


def test_missing_pose(log_copy):
    root, log_dir = log_copy
    poses = pd.read_feather(log_dir / "city_SE3_egovehicle.feather")
    poses[poses["timestamp_ns"] != STAMP1].reset_index(drop=True).to_feather(log_dir / "city_SE3_egovehicle.feather")
    assert f"city_SE3_egovehicle.feather: 0 poses for timestamp {STAMP1}" in _read_error(root)


def test_missing_annotation_column(log_copy):
    root, log_dir = log_copy
    annotations = pd.read_feather(log_dir / "annotations.feather")
    annotations.drop(columns="track_uuid").to_feather(log_dir / "annotations.feather")
    assert "annotations.feather: missing column(s) track_uuid" in _read_error(root)


def test_missing_ground_raster(log_copy):
    root, log_dir = log_copy
    for raster in (log_dir / "map").glob("*ground_height*"):
        raster.unlink()
    assert "map: cannot read the ground height raster" in _read_error(root)


def test_without_annotations_there_is_no_flow(log_copy):
    root, log_dir = log_copy
    (log_dir / "annotations.feather").unlink()
    pair = AV2Dataset(root, "val").pair(0)
    assert pair.flow is None and pair.classes is None and pair.ground0 is not None


def test_longer_horizon(log_copy):
    """A third sweep (sweep 1's points filed under the next annotated timestamp) gives the pair (0, 2)."""
    root, log_dir = log_copy
    stamp2 = 315966265459565000
    shutil.copy(_sweep(log_dir, STAMP1), _sweep(log_dir, stamp2))
    dataset = AV2Dataset(root, "val", max_horizon=2)
    assert len(dataset) == 1
    pair = dataset.pair(0, horizon=2)
    assert pair.timestamp1_ns == stamp2 and pair.dt == pytest.approx(0.199729)
    assert pair.sample_id == f"{LOG}/{STAMP0}+2"
    residual = np.linalg.norm(pair.residual_flow(), axis=1)
    np.testing.assert_array_equal(pair.dynamic, residual >= 0.1)  # 0.5 m/s over two sweeps
    static = pair.classes == 0
    assert static.sum() > 80_000  # 89,832 of 99,229 points of class 0 (background): not an empty selection
    np.testing.assert_allclose(pair.flow[static], pair.ego_flow()[static], atol=1e-5)
    one_step = AV2Dataset(root, "val", max_horizon=2).pair(0, horizon=1)
    moving = one_step.dynamic & pair.dynamic
    assert moving.sum() > 1000  # the movers of one step keep moving: about twice the displacement over two
    ratio = residual[moving] / np.linalg.norm(one_step.residual_flow()[moving], axis=1)
    assert 1.7 < np.median(ratio) < 2.3
    with pytest.raises(IndexError):
        dataset.pair(0, horizon=3)


def test_a_sweep_that_claims_more_rows_than_the_cap_is_refused_before_it_is_decompressed(tmp_path):
    """Issue 45.1: an LZ4 feather of 6e6 rows of zeros is 120 KB; its rows are read from the batches' metadata and
    refused in one line before pyarrow decompresses a byte (peak memory barely grown)."""
    import resource

    import pyarrow as pa
    import pyarrow.feather as feather

    from icpflow.datasets.file_formats import read_feather

    zeros = np.zeros(6_000_000, np.float16)
    path = tmp_path / "bomb.feather"
    feather.write_feather(pa.table({"x": zeros, "y": zeros, "z": zeros}), str(path), compression="lz4")
    del zeros
    assert path.stat().st_size < 1_000_000
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(FramePairError, match=r"bomb.feather: its record batches claims 6000000 rows .* over the cap"):
        read_feather(path, ("x", "y", "z"))
    assert (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak) * 1024 < 50e6
