"""The 3D viewer (icpflow.viz.recording): recordings written, then read back through rerun's own reader, entity by
entity and value by value; from eval.py viewer=rerun and fastflow3d-infer --rerun (on the shipped KITTI scans)."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from icpflow.core.geometry import full_to_residual, transform_points
from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.evaluation import run_eval
from icpflow.evaluation.baselines import ego_only_flow, zero_flow
from icpflow.viz.recording import PairRecording, ViewerUnavailable, import_rerun, speed_colours

pytest.importorskip("rerun", reason="rerun-sdk is an optional dependency (pip install 'icpflow[viz]')")
from helpers.data import REPO, needs_shared, shared  # noqa: E402
from helpers.rerun import read_recording  # noqa: E402

KITTI = shared("kitti_hdl64_scans")
READER = {"split": "val", "num_sequences": 1, "frames_per_sequence": 3, "beams": 32, "azimuth_resolution_deg": 1.0}


def rgb(packed: np.ndarray) -> np.ndarray:
    """rerun's packed 0xRRGGBBAA colours as (N, 3) uint8."""
    packed = np.asarray(packed, np.uint32)
    return np.stack([(packed >> 24) & 255, (packed >> 16) & 255, (packed >> 8) & 255], axis=1).astype(np.uint8)


@pytest.fixture(scope="module")
def pairs():
    dataset = SyntheticDataset(**READER)
    return [dataset.pair(i) for i in range(len(dataset))]


def test_recording_holds_scans_flows_masks_on_a_timeline(pairs, tmp_path):
    path = tmp_path / "run" / "pairs.rrd"
    rng = np.random.default_rng(0)
    in_grid = [rng.random(len(pair.pc0)) < 0.5 for pair in pairs]
    with PairRecording(path) as recording:
        for step, pair in enumerate(pairs):
            flows = {"zero": zero_flow(pair), "ego": ego_only_flow(pair)}
            recording.log_pair(step, pair, flows, in_grid=in_grid[step])
    assert path.is_file() and [p.name for p in path.parent.iterdir()] == ["pairs.rrd"]  # no temporary left
    entities = read_recording(path)
    methods = ("zero", "ego", "ground_truth")  # the pairs have ground truth: recorded as one more method
    expected = {"pc0", "pc1", "masks/ground0", "masks/in_grid", "info"}
    expected |= {f"flow/{m}/{part}" for m in methods for part in ("moved", "vectors")}
    assert set(entities) == expected
    for step, pair in enumerate(pairs):
        moved = transform_points(pair.ego1_from_ego0, pair.pc0)
        assert sorted(entities["pc0"]) == list(range(len(pairs)))  # the timeline: one step per pair
        np.testing.assert_allclose(entities["pc0"][step]["positions"], moved, atol=1e-5)
        np.testing.assert_array_equal(entities["pc1"][step]["positions"], pair.pc1)
        np.testing.assert_allclose(entities["masks/ground0"][step]["positions"], moved[pair.ground0], atol=1e-5)
        np.testing.assert_allclose(entities["masks/in_grid"][step]["positions"], moved[in_grid[step]], atol=1e-5)
        for name, flow in {"zero": zero_flow(pair), "ego": ego_only_flow(pair), "ground_truth": pair.flow}.items():
            speed = np.linalg.norm(full_to_residual(flow, pair.pc0, pair.ego1_from_ego0), axis=1) / pair.dt
            points = entities[f"flow/{name}/moved"][step]
            np.testing.assert_allclose(points["positions"], pair.pc0 + flow, atol=1e-5)
            np.testing.assert_array_equal(rgb(points["colors"]), speed_colours(speed))
            arrows, moving = entities[f"flow/{name}/vectors"][step], speed >= 0.5
            if name == "ego":  # every point static in the world: no arrow
                assert not moving.any() and arrows.get("vectors", np.zeros((0, 3))).size == 0
            else:
                assert moving.sum() > 100
                np.testing.assert_allclose(arrows["origins"], moved[moving], atol=1e-5)
                np.testing.assert_allclose(arrows["vectors"], (pair.pc0 + flow - moved)[moving], atol=1e-4)
        assert pair.sample_id in entities["info"][step]["text"][0]


def test_speed_colours_ramp_and_clip():
    colours = speed_colours(np.array([0.0, 5.0, 10.0, 50.0]), max_speed=10.0)
    assert colours.dtype == np.uint8 and colours.shape == (4, 3)
    assert np.array_equal(colours[2], colours[3]) and not np.array_equal(colours[0], colours[1])


def test_without_rerun_one_line_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun now raises ImportError
    with pytest.raises(ViewerUnavailable, match=r"^the 3D viewer needs the rerun-sdk package: pip install"):
        import_rerun()


def _cfg(out_dir, *overrides):
    small = [f"dataset.reader.{key}={value}" for key, value in READER.items() if key != "split"]
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose("eval", [*small, f"out_dir={out_dir}", "bev=0", *overrides])


def test_eval_viewer_rerun_records_every_method(pairs, tmp_path, capsys):
    assert run_eval(_cfg(tmp_path, "viewer=rerun", "viewer_pairs=1", "method=[zero,ego]"), progress=False) == 0
    entities = read_recording(tmp_path / "recording.rrd")
    assert {"flow/zero/moved", "flow/ego/moved", "flow/ground_truth/moved", "masks/ground0"} <= set(entities)
    assert list(entities["pc0"]) == [0]  # viewer_pairs=1 of the 2 pairs scored
    np.testing.assert_allclose(entities["flow/ego/moved"][0]["positions"], pairs[0].pc0 + ego_only_flow(pairs[0]))
    assert f"recording of 1 pairs -> {tmp_path / 'recording.rrd'}" in capsys.readouterr().out
    assert run_eval(_cfg(tmp_path / "bad", "viewer=open3d"), progress=False) == 2
    assert "eval: viewer must be one of rerun, null, got 'open3d'" in capsys.readouterr().err


@needs_shared("kitti_hdl64_scans", "000001.bin", what="the shipped KITTI HDL-64 scans", kind="file")
def test_infer_rerun_on_kitti_scans(tiny_student, tmp_path):
    from fastflow3d.inference.cli import main as infer_main

    out, recording = tmp_path / "flow.npz", tmp_path / "kitti.rrd"
    scans = [str(KITTI / "000000.bin"), str(KITTI / "000001.bin")]
    assert infer_main([str(tiny_student), *scans, "--out", str(out), "--no-bev", "--rerun", str(recording)]) == 0
    entities = read_recording(recording)
    assert {"pc0", "pc1", "flow/fastflow3d/moved", "flow/fastflow3d/vectors", "masks/in_grid"} <= set(entities)
    with np.load(out) as result:
        pc0 = np.fromfile(scans[0], np.float32).reshape(-1, 4)[:, :3]
        moved = transform_points(result["ego1_from_ego0"], pc0)
        np.testing.assert_allclose(entities["pc0"][0]["positions"], moved, atol=1e-4)
        np.testing.assert_allclose(entities["flow/fastflow3d/moved"][0]["positions"], pc0 + result["flow"], atol=1e-5)
        np.testing.assert_allclose(entities["masks/in_grid"][0]["positions"], moved[result["in_grid"]], atol=1e-4)


@needs_shared("kitti_hdl64_scans", "000001.bin", what="the shipped KITTI HDL-64 scans", kind="file")
@pytest.mark.parametrize("place", ["full", "read-only"])
def test_a_recording_on_a_full_or_read_only_place_is_one_line_naming_it(tiny_student, tmp_path, mount_tmpfs, place):
    """Issue 31.5: ``fastflow3d-infer --rerun`` where the file cannot be written: one line naming the file asked for
    (not rerun's temporary name), none of rerun's own log lines, exit 2, nothing left there. A process of its own:
    rerun's Rust logging is set when rerun is first imported, which this test module has already done."""
    import subprocess

    disk = mount_tmpfs(tmp_path / "disk", "64k", read_only=place == "read-only")
    recording = disk / "pair.rrd"
    scans = [str(KITTI / "000000.bin"), str(KITTI / "000001.bin"), "--sensor-height", "1.73"]
    command = [
        sys.executable,
        "-m",
        "fastflow3d.inference.cli",
        str(tiny_student),
        *scans,
        "--no-bev",
        "--rerun",
        str(recording),
    ]
    result = subprocess.run(command + ["--out", str(tmp_path / "f.npz")], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2, result.stderr
    assert result.stderr.startswith(f"infer: {recording}: cannot write ("), result.stderr
    assert result.stderr.count("\n") == 1 and ".tmp-" not in result.stderr, result.stderr
    assert ("No space left" if place == "full" else "Read-only") in result.stderr, result.stderr
    assert list(disk.iterdir()) == []
