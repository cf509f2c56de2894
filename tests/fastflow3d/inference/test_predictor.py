"""The Predictor on arrays: the ego motion it estimates, ground removal, bad inputs refused, scans in another frame
lifted, implausible ground warned, kernels never run from a stale cache, the refinement opt-in."""

import json
import warnings

import numpy as np
import pytest
import torch

from fastflow3d.artifact.file_format import FILE_NAMES, METADATA_NAME, ArtifactError
from fastflow3d.inference.cli import main as infer_main
from fastflow3d.inference.prediction import PredictorError, PredictorWarning
from fastflow3d.inference.predictor import Predictor
from fastflow3d.network.model import compensate
from icpflow.core.geometry import ego_flow, residual_to_full
from icpflow.scans.ground import GroundSegmenter
from icpflow.scans.preprocess import Preprocessing

from helpers.exports import (
    TOLERANCE,
    lowered,
    write_poses,
    write_scan,
)

pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript")


def test_predictor_estimates_ego_motion_without_transform(export_dir, pairs, teacher_ego):
    pair = pairs[1]
    predictor = Predictor.load(export_dir)
    estimated = predictor.predict(pair.pc0, pair.pc1)
    assert estimated.ego_estimated
    # the teacher's step 1 with the teacher's default settings, then the same as with that transform given
    np.testing.assert_allclose(estimated.ego1_from_ego0, teacher_ego, atol=1e-9)
    assert np.abs(teacher_ego[:3, 3] - pair.ego1_from_ego0[:3, 3]).max() < 0.1  # KISS-ICP here: a few cm
    given = predictor.predict(pair.pc0, pair.pc1, teacher_ego)
    assert not given.ego_estimated
    np.testing.assert_allclose(estimated.flow, given.flow, atol=1e-6, rtol=0)


def test_ground_removal_model_sees_non_ground_points_only(ground_checkpoint, ground_export, eager, pairs, tmp_path):
    path, teacher = ground_checkpoint
    export_dir = ground_export
    stored = json.loads((export_dir / METADATA_NAME).read_text())["input"]
    assert stored["remove_ground"] is True and stored["ground"]["sensor_height"] == 1.9
    assert stored["frame"] == {"ground_z": 0.0} and stored["version"] == 2
    pair = pairs[0]
    ground0, ground1 = GroundSegmenter(teacher)(pair.pc0), GroundSegmenter(teacher)(pair.pc1)
    assert 0.2 < ground0.mean() < 0.9 and 0.2 < ground1.mean() < 0.9

    def expected_flow(g0, g1):
        with torch.no_grad():
            kept, valid = eager(
                torch.from_numpy(compensate(pair.pc0[~g0], pair.ego1_from_ego0)), torch.from_numpy(pair.pc1[~g1])
            )
        residual = np.zeros_like(pair.pc0)
        residual[~g0] = kept.numpy()
        return residual_to_full(residual, pair.pc0, pair.ego1_from_ego0), valid.numpy()

    flow, valid = expected_flow(ground0, ground1)
    ego = ego_flow(pair.pc0, pair.ego1_from_ego0)
    for predictor in (Predictor.load(path), Predictor.load(export_dir)):
        assert predictor.remove_ground and predictor.preprocessing == Preprocessing.from_teacher(teacher)
        prediction = predictor.predict(pair.pc0, pair.pc1, pair.ego1_from_ego0)  # masks computed as the teacher does
        assert np.array_equal(prediction.ground0, ground0) and np.array_equal(prediction.in_grid[~ground0], valid)
        assert not prediction.in_grid[ground0].any()
        np.testing.assert_allclose(prediction.flow[ground0], ego[ground0], atol=1e-6, rtol=0)
        assert np.abs(prediction.flow - flow).max() <= TOLERANCE
    # masks passed in are used as given (here the synthetic world's exact ground)
    given = predictor.predict(pair.pc0, pair.pc1, pair.ego1_from_ego0, pair.ground0, pair.ground1)
    assert np.array_equal(given.ground0, pair.ground0) and not np.array_equal(pair.ground0, ground0)
    assert np.abs(given.flow - expected_flow(pair.ground0, pair.ground1)[0]).max() <= TOLERANCE
    with pytest.raises(PredictorError, match=r"ground1 must be a bool \(\d+,\) mask"):
        predictor(pair.pc0, pair.pc1, pair.ego1_from_ego0, pair.ground0, pair.ground1[1:])
    # the CLI on raw files: masks computed, written with the flow
    scan0, scan1 = write_scan(tmp_path / "a.npy", pair.pc0), write_scan(tmp_path / "b.npy", pair.pc1)
    poses, out = write_poses(tmp_path / "poses.txt", [pair.pose0, pair.pose1]), tmp_path / "flow.npz"
    assert infer_main([str(export_dir), str(scan0), str(scan1), "--poses", str(poses), "--out", str(out)]) == 0
    with np.load(out) as result:
        assert np.array_equal(result["ground0"], ground0) and np.abs(result["flow"] - flow).max() <= TOLERANCE


def test_predictor_rejects_bad_inputs(export_dir, tmp_path):
    predictor = Predictor.load(export_dir)
    points = np.zeros((10, 3), np.float32)
    with pytest.raises(PredictorError, match=r"Predictor: pc1 must be a numeric \(N, 3\) array"):
        predictor(points, np.zeros((10, 2), np.float32), np.eye(4))
    with pytest.raises(PredictorError, match=r"Predictor: pc0 has shape \(3, 10\): a transposed scan\?"):
        predictor(np.zeros((3, 10), np.float32), points, np.eye(4))
    with pytest.raises(PredictorError, match=r"Predictor: pc0 has 1 rows with NaN or Inf \(of 10\)"):
        predictor(np.vstack([points[:9], [[np.nan, 0, 0]]]), points, np.eye(4))
    with pytest.raises(PredictorError, match="not rigid"):
        predictor(points, points, np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(ArtifactError, match="not an export directory"):
        Predictor.load(tmp_path)
    copy = tmp_path / "copy"
    copy.mkdir()
    for name in (METADATA_NAME, FILE_NAMES["pt2"]):
        (copy / name).write_bytes((export_dir / name).read_bytes())
    (copy / FILE_NAMES["pt2"]).write_bytes(b"changed")
    with pytest.raises(ArtifactError, match="changed after export"):
        Predictor.load(copy, backend="pt2")


def test_a_predictor_never_runs_kernels_of_a_stale_cache(export_dir, pairs, monkeypatch):
    """Every Predictor (``fastflow3d-infer``, a stream, a Python caller) checks the numba cache before its first
    pair, never in its constructor (``icpflow.teacher.warmup.prepare_kernels``: a cache of other sources emptied;
    each kernel it calls compiled on its first call, not all of the teacher's), and once per process."""
    from fastflow3d.inference import predictor as predictor_module
    from fastflow3d.inference.stream import FlowStream
    from icpflow.teacher import warmup

    asked = []
    monkeypatch.setattr(predictor_module, "prepare_kernels", lambda prefix: asked.append(prefix))
    predictor = Predictor.load(export_dir)
    assert asked == []  # loading compiles, empties and prints nothing
    predictor.predict(pairs[0].pc0, pairs[0].pc1, pairs[0].ego1_from_ego0)
    assert asked == ["fastflow3d"]
    FlowStream(predictor).push(pairs[0].pc0)
    assert asked == ["fastflow3d"] * 2
    # the step itself runs once per process: a stale cache is emptied, and said, at the first call only
    emptied = []
    monkeypatch.setattr(warmup, "ensure_compiled", lambda prefix, eager: emptied.append((prefix, eager)) or True)
    warmup.prepare_kernels.cache_clear()
    try:
        assert warmup.prepare_kernels("fastflow3d") is True and warmup.prepare_kernels("fastflow3d") is True
        assert emptied == [("fastflow3d", False)]
    finally:
        warmup.prepare_kernels.cache_clear()


def test_scans_in_a_sensor_frame_are_lifted_never_run_silently(export_dir, pairs, expected):
    """A pair given in a sensor frame (ground 1.73 m below the origin) against a model of the ground-level frame:
    sensor_height=1.73 lifts it exactly (same flow, the ego motion returned in the given frame); the default
    (None) notices the mismatch, lifts by the estimated ground and warns in one line; 'auto' lifts silently."""
    pair, (flow, valid) = pairs[0], expected[0]
    pc0, pc1, ego = lowered(pair, 1.73)
    predictor = Predictor.load(export_dir, sensor_height=1.73)
    with warnings.catch_warnings():
        warnings.simplefilter("error", PredictorWarning)
        told = predictor.predict(pc0, pc1, ego)
    assert told.lift == pytest.approx(1.73) and np.array_equal(told.in_grid, valid)
    np.testing.assert_allclose(told.ego1_from_ego0, ego, atol=1e-12)
    assert np.abs(told.flow - flow).max() <= 1e-3  # float32 rounding of the lifted z only
    with pytest.warns(PredictorWarning, match=r"ground of pc0 lies at z = -1\.\d\d m .* lifted by \+1\.\d\d m") as seen:
        guessed = Predictor.load(export_dir).predict(pc0, pc1, ego)
    assert all("\n" not in str(w.message) for w in seen)
    assert abs(guessed.lift - 1.73) < 0.1 and np.abs(guessed.flow - flow).mean() < 0.02
    auto = Predictor.load(export_dir, sensor_height="auto").predict(pc0, pc1, ego)
    assert auto.lift == pytest.approx(guessed.lift)
    # in its own frame nothing moves: no lift, no frame warning, the flow as before
    same = Predictor.load(export_dir).predict(pair.pc0, pair.pc1, pair.ego1_from_ego0)
    assert same.lift == 0.0 and np.abs(same.flow - flow).max() <= TOLERANCE
    with pytest.raises(PredictorError, match="sensor_height='high' must be None, 'auto' or metres"):
        Predictor.load(export_dir, sensor_height="high")


def test_implausible_ground_is_warned(ground_checkpoint, pairs):
    """Scans left in a sensor frame 3.5 m above the ground (told wrongly that they are in the model's:
    sensor_height=0) put nearly every point under the z threshold: more than 85 % ground gives a one-line
    warning."""
    path, _ = ground_checkpoint
    pc0, pc1, ego = lowered(pairs[0], 3.5)
    with pytest.warns(PredictorWarning, match=r"implausible preprocessing of pc0: \d+% of the points called ground"):
        prediction = Predictor.load(path, sensor_height=0.0).predict(pc0, pc1, ego)
    assert prediction.ground0.mean() > 0.85
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PredictorWarning)
        right = Predictor.load(path, sensor_height=3.5).predict(pc0, pc1, ego)
    assert right.ground0.mean() < 0.85 and not [w for w in caught if "called ground" in str(w.message)]


def test_predictor_refinement_is_opt_in_and_checked(export_dir, pairs, tmp_path):
    pair = pairs[0]
    plain = Predictor.load(export_dir).predict(pair.pc0, pair.pc1, pair.ego1_from_ego0)
    assert plain.refined is None
    refined = Predictor.load(export_dir, refine=True).predict(pair.pc0, pair.pc1, pair.ego1_from_ego0)
    assert refined.refined.shape == (len(pair.pc0),) and not refined.refined[~refined.in_grid].any()
    # the points ICP did not take keep the network's flow; the others moved rigidly per component
    kept = ~refined.refined
    np.testing.assert_array_equal(refined.flow[kept], plain.flow[kept])
    with pytest.raises(PredictorError, match="unknown settings"):
        Predictor.load(export_dir, refine={"cells": 1.0})
    # the inference CLI: --refine writes the refined flow and its mask
    poses = write_poses(tmp_path / "poses.txt", [pair.pose0, pair.pose1])
    scan0, scan1 = write_scan(tmp_path / "a.npy", pair.pc0), write_scan(tmp_path / "b.npy", pair.pc1)
    out = tmp_path / "flow.npz"
    assert (
        infer_main(
            [str(export_dir), str(scan0), str(scan1), "--poses", str(poses), "--out", str(out), "--no-bev", "--refine"]
        )
        == 0
    )
    with np.load(out) as result:
        assert np.array_equal(result["refined"], refined.refined)
        assert np.abs(result["flow"] - refined.flow).max() <= TOLERANCE
