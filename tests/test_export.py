"""Export (ONNX, torch.export) parity with eager, older TorchScript exports, the Predictor on arrays and raw scan
files, and the CLIs' errors.

The tiny FastFlow3D of the tests (helpers.training.TINY_MODEL: +-16 m, 1 m cells, 32 x 32 grid) is trained a few
steps on a synthetic pair so that its weights and BatchNorm statistics are not the initial ones, saved as a training
checkpoint (the checkpoint contract of ``fastflow3d.artifact.checkpoint``) and exported once for the whole module.
"""

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from fastflow3d.artifact.checkpoint import load_student
from fastflow3d.artifact.export import export_checkpoint, run_export
from fastflow3d.artifact.file_format import FILE_NAMES, METADATA_NAME, ArtifactError, SingleSampleNet, sha256_file
from fastflow3d.inference.cli import main as infer_main
from fastflow3d.inference.prediction import PredictorError, PredictorWarning
from fastflow3d.inference.predictor import Predictor
from fastflow3d.network.contract import ContractError, upgrade
from fastflow3d.network.model import compensate
from fastflow3d.network.voxelize import Grid
from icpflow import __version__
from icpflow.core.geometry import ego_flow, residual_to_full
from icpflow.core.open3d_loader import load_open3d
from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.scans.ground import GroundSegmenter
from icpflow.scans.odometry import estimate_ego_motion
from icpflow.scans.preprocess import Preprocessing, lift_points, lift_transform
from icpflow.teacher.config import ICPFlowConfig

from helpers.students import tiny_checkpoint  # tests/ is on sys.path (pytest prepend import mode)
from helpers.training import TINY_MODEL

pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript")

REPO = Path(__file__).resolve().parents[1]
NEAR = TINY_MODEL["x_range"][1] + 0.6  # m: points this far from the sensor (x and y) are near the grid
TOLERANCE = 1e-4  # metres


@pytest.fixture(scope="module")
def pairs():
    """Synthetic pairs with different point counts: a whole pair and two random subsets of the next one."""
    dataset = SyntheticDataset(split="test", beams=32, num_sequences=1, frames_per_sequence=3, seed=0)
    whole, other = dataset[0], dataset[1]
    rng = np.random.default_rng(0)
    subsets = []
    for n0, n1 in [(9000, 31000), (20000, 700)]:
        keep0, keep1 = rng.choice(len(other.pc0), n0, replace=False), rng.choice(len(other.pc1), n1, replace=False)
        subsets.append(
            other.replace(
                pc0=other.pc0[keep0],
                pc1=other.pc1[keep1],
                flow=other.flow[keep0],
                ground0=None,
                ground1=None,
                flow_valid=None,
                classes=None,
                instance=None,
                dynamic=None,
            )
        )
    return [whole, *subsets]


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory, pairs):
    """A training checkpoint of the tiny model after 15 Adam steps towards one pair's true residual flow (on 6000
    points of each scan near the grid, to keep it fast)."""
    pair = pairs[0]
    near0 = np.flatnonzero(np.abs(pair.pc0[:, :2]).max(axis=1) < NEAR)[:6000]
    near1 = np.flatnonzero(np.abs(pair.pc1[:, :2]).max(axis=1) < NEAR)[:6000]
    path = tmp_path_factory.mktemp("run") / "best.ckpt"
    return tiny_checkpoint(path, pair, 15, near0, near1)


@pytest.fixture(scope="module")
def export_dir(checkpoint):
    return export_checkpoint(checkpoint)


@pytest.fixture(scope="module")
def eager(checkpoint):
    """The trained tiny network in eval mode, from the checkpoint."""
    return SingleSampleNet(load_student(checkpoint)[0]).eval()


def eager_full_flow(net, pair):
    with torch.no_grad():
        residual, valid = net(torch.from_numpy(compensate(pair.pc0, pair.ego1_from_ego0)), torch.from_numpy(pair.pc1))
    return residual_to_full(residual.numpy(), pair.pc0, pair.ego1_from_ego0), valid.numpy()


@pytest.fixture(scope="module")
def expected(eager, pairs):
    """Eager full flow and in-grid mask of every pair (given ego motion)."""
    return [eager_full_flow(eager, pair) for pair in pairs]


@pytest.fixture(scope="module")
def teacher_ego(pairs, export_dir):
    """The teacher's ego-motion estimate (step 1, default settings: the odometry of the two scans without their
    ground's surface, found with the model's settings) of the smallest pair."""
    pair = pairs[1]
    segmenter = GroundSegmenter(Predictor.load(export_dir).preprocessing)
    surface0, surface1 = segmenter.masks(pair.pc0)[1], segmenter.masks(pair.pc1)[1]
    return estimate_ego_motion(pair.pc0, pair.pc1, ICPFlowConfig(), surface0, surface1)


def test_metadata_describes_the_export(export_dir, checkpoint):
    assert export_dir == checkpoint.parent / "export"
    metadata = json.loads((export_dir / METADATA_NAME).read_text())
    assert metadata["grid"] == {
        "x_range": [-16.0, 16.0],
        "y_range": [-16.0, 16.0],
        "z_range": [-3.0, 3.0],
        "cell": 1.0,
        "nx": 32,
        "ny": 32,
    }
    assert metadata["model"].items() >= TINY_MODEL.items()
    assert metadata["package_version"] == __version__
    assert metadata["source_checkpoint"]["sha256"] == sha256_file(checkpoint)
    assert [entry["name"] for entry in metadata["inputs"]] == ["pc0_compensated", "pc1"]
    assert [entry["name"] for entry in metadata["outputs"]] == ["residual", "valid"]
    assert "ego1_from_ego0 * pc0 - pc0" in metadata["flow_convention"]
    # a checkpoint whose config has no data block (trained on every point, default teacher settings)
    contract = upgrade(metadata)
    assert metadata["input"]["version"] == 2 and metadata["input"]["remove_ground"] is False
    assert contract.preprocessing.frame.ground_z == 0.0  # trained in the synthetic frame
    assert contract.grid == Grid((-16.0, 16.0), (-16.0, 16.0), (-3.0, 3.0), 1.0)
    for name in ("onnx", "pt2"):
        entry = metadata["files"][name]
        assert entry["path"] == FILE_NAMES[name] and entry["sha256"] == sha256_file(export_dir / entry["path"])
        assert metadata["parity_max_abs_m"][name] <= TOLERANCE
    assert sorted(p.name for p in export_dir.iterdir()) == sorted([METADATA_NAME, *FILE_NAMES.values()])


@pytest.mark.parametrize("backend", ["onnx", "pt2"])
def test_export_parity_on_synthetic_pairs(export_dir, expected, pairs, backend):
    predictor = Predictor.load(export_dir, backend=backend)
    assert predictor.backend == backend
    moving = 0
    for pair, (flow, valid) in zip(pairs, expected):
        prediction = predictor.predict(pair.pc0, pair.pc1, pair.ego1_from_ego0)
        assert prediction.flow.shape == (len(pair.pc0), 3) and prediction.flow.dtype == np.float32
        assert np.array_equal(prediction.in_grid, valid) and 0 < valid.sum() < len(valid)
        assert np.abs(prediction.flow - flow).max() <= TOLERANCE
        # outside the grid: the ego flow exactly; inside: what the network adds on top of it
        ego = ego_flow(pair.pc0, pair.ego1_from_ego0)
        np.testing.assert_allclose(prediction.flow[~valid], ego[~valid], atol=1e-6, rtol=0)
        moving += int((np.linalg.norm(prediction.residual[valid], axis=1) > 0.05).sum())
    assert moving > 100  # a trained network that predicts motion, not a near-zero one that passes any tolerance


def test_checkpoint_and_single_files_load(export_dir, checkpoint, expected, pairs):
    pair, (flow, _) = pairs[2], expected[2]
    from_ckpt = Predictor.load(checkpoint)
    assert from_ckpt.backend == "eager" and from_ckpt.metadata["grid"]["nx"] == 32
    np.testing.assert_allclose(from_ckpt(pair.pc0, pair.pc1, pair.ego1_from_ego0), flow, atol=1e-6, rtol=0)
    for name, backend in (("fastflow3d.onnx", "onnx"), ("fastflow3d.pt2", "pt2")):
        predictor = Predictor.load(export_dir / name)
        assert predictor.backend == backend and predictor.metadata["model"].items() >= TINY_MODEL.items()
        assert np.abs(predictor(pair.pc0, pair.pc1, pair.ego1_from_ego0) - flow).max() <= TOLERANCE


def test_older_torchscript_exports_load_only_when_asked_for(export_dir, eager, expected, pairs, tmp_path):
    """An export directory of an older version (``fastflow3d.pt``, TorchScript, listed as ``torchscript``) runs as
    before, by directory and as a bare file, when the caller names the backend (with a warning that TorchScript
    runs code); without it, it is refused in one line (a TorchScript file can run any code when loaded)."""
    legacy = tmp_path / "legacy"
    legacy.mkdir()
    example = tuple(torch.from_numpy(cloud[:500]) for cloud in (pairs[0].pc0, pairs[0].pc1))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", (DeprecationWarning, FutureWarning))  # torch.jit is deprecated
        torch.jit.save(torch.jit.trace(eager, example, check_trace=False), str(legacy / "fastflow3d.pt"))
    metadata = json.loads((export_dir / METADATA_NAME).read_text())
    metadata["files"] = {"torchscript": {"path": "fastflow3d.pt", "sha256": sha256_file(legacy / "fastflow3d.pt")}}
    (legacy / METADATA_NAME).write_text(json.dumps(metadata))
    pair, (flow, _) = pairs[2], expected[2]
    for path in (legacy, legacy / "fastflow3d.pt"):
        with pytest.raises(ArtifactError, match="runs code when it is loaded") as caught:
            Predictor.load(path)
        assert "\n" not in str(caught.value) and str(path) in str(caught.value)
    for path in (legacy, legacy / "fastflow3d.pt"):
        with pytest.warns(UserWarning, match="runs code when it is loaded"):
            predictor = Predictor.load(path, backend="torchscript")
        assert predictor.backend == "torchscript" and predictor.metadata["model"].items() >= TINY_MODEL.items()
        assert np.abs(predictor(pair.pc0, pair.pc1, pair.ego1_from_ego0) - flow).max() <= TOLERANCE


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


#: the flat ICPFlowConfig fields that checkpoints of older versions saved as ``data.teacher`` (before the typed
#: block and the teacher's ground / ego_motion blocks), with the synthetic dataset's values
LEGACY_TEACHER = dict(ground="both", sensor_height=1.9, patchwork_max_range=64.0, patchwork_z_offset=-1.9, range_z=0.04)
LEGACY_TEACHER.update(ground_slack=0.3, kiss_voxel_size=1.0, kiss_max_range=100.0, ego_refine_voxel=0.2)


@pytest.fixture(scope="module")
def ground_checkpoint(checkpoint):
    """The same trained weights in a checkpoint of an older version whose config says the network saw non-ground
    points only, with the teacher settings of the synthetic dataset (a 1.9 m high sensor over a z = 0 ground) as a
    flat ``data.teacher`` dict (before the typed preprocessing block)."""
    teacher = ICPFlowConfig.preset(
        "waymo", ground={"method": "both", "sensor_height": 1.9, "patchwork_z_offset": -1.9}
    )  # the ground of that version, as its flat dict says
    saved = torch.load(checkpoint, weights_only=True)
    del saved["hyper_parameters"]["cfg"]["input"]  # older versions stored no input contract
    saved["hyper_parameters"]["cfg"]["data"] = {
        "remove_ground": True,
        "teacher": dict(LEGACY_TEACHER),
    }
    path = checkpoint.parent / "ground" / "best.ckpt"
    path.parent.mkdir()
    torch.save(saved, path)
    return path, teacher


@pytest.fixture(scope="module")
def ground_export(ground_checkpoint):
    """The ground-removal checkpoint exported (pt2 only)."""
    return export_checkpoint(ground_checkpoint[0], formats=("pt2",))


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


def write_scan(path: Path, points: np.ndarray) -> Path:
    """Write (N, 3) float32 points in the format of ``path``'s suffix."""
    suffix = path.suffix
    if suffix == ".bin":
        np.c_[points, np.ones(len(points))].astype(np.float32).tofile(path)
    elif suffix == ".npy":
        np.save(path, points)
    elif suffix == ".npz":
        np.savez(path, points=points)
    else:
        o3d = load_open3d()
        o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.astype(float))))
    return path


def write_poses(path: Path, poses) -> Path:
    path.write_text("".join(" ".join(f"{v:.12g}" for v in pose[:3].ravel()) + "\n" for pose in poses))
    return path


def test_infer_cli_on_raw_files_with_and_without_poses(export_dir, pairs, expected, teacher_ego, tmp_path, capsys):
    pair, (flow, valid) = pairs[1], expected[1]
    poses = write_poses(tmp_path / "poses.txt", [pair.pose0, pair.pose1])
    for suffix0, suffix1, bev in ((".bin", ".npz", []), (".ply", ".pcd", ["--no-bev"])):
        scan0, scan1 = write_scan(tmp_path / f"a{suffix0}", pair.pc0), write_scan(tmp_path / f"b{suffix1}", pair.pc1)
        out = tmp_path / f"flow{suffix0}.npz"
        args = [str(export_dir), str(scan0), str(scan1), "--poses", str(poses), "--out", str(out), *bev]
        assert infer_main(args) == 0
        with np.load(out) as result:
            assert not result["ego_estimated"]
            np.testing.assert_allclose(result["ego1_from_ego0"], pair.ego1_from_ego0, atol=1e-9)
            assert np.abs(result["flow"] - flow).max() <= TOLERANCE
            assert np.array_equal(result["in_grid"], valid)
        assert out.with_suffix(".png").is_file() == (not bev)
    assert (tmp_path / "flow.bin.png").stat().st_size > 10_000
    scan0, scan1 = write_scan(tmp_path / "a.npy", pair.pc0), write_scan(tmp_path / "b.npy", pair.pc1)
    out = tmp_path / "estimated.npy"
    assert infer_main([str(export_dir / "fastflow3d.pt2"), str(scan0), str(scan1), "--out", str(out), "--no-bev"]) == 0
    got = np.load(out)
    assert got.shape == pair.pc0.shape and got.dtype == np.float32
    with_teacher_ego = Predictor.load(export_dir).predict(pair.pc0, pair.pc1, teacher_ego)
    assert np.abs(got - with_teacher_ego.flow).max() <= TOLERANCE
    assert "flow ->" in capsys.readouterr().out


def test_infer_cli_errors_are_one_line(export_dir, pairs, tmp_path, capsys):
    pair = pairs[2]
    good0, good1 = write_scan(tmp_path / "a.npy", pair.pc0), write_scan(tmp_path / "b.npy", pair.pc1)
    truncated = tmp_path / "cut.bin"
    truncated.write_bytes(np.ones(4 * 100 + 2, np.float32).tobytes())
    unnamed = tmp_path / "keys.npz"
    np.savez(unnamed, xyz=pair.pc0)
    three = write_poses(tmp_path / "three.txt", [np.eye(4)] * 3)
    sheared = tmp_path / "sheared.npy"
    np.save(sheared, np.diag([1.0, 2.0, 1.0, 1.0]))
    cases = [
        ([good0, tmp_path / "missing.npy"], "missing.npy: file not found"),
        ([truncated, good1], "cut.bin: size"),
        ([unnamed, good1], "keys.npz: no array named points or pc"),
        ([good0, tmp_path / "scan.xyz"], "scan.xyz: unsupported scan format"),
        ([good0, good1, "--poses", three], "three.txt: holds 3 transform(s), expected 2"),
        ([good0, good1, "--ego", sheared], "sheared.npy: transform 1 is not rigid"),
    ]
    for args, message in cases:
        assert infer_main([str(export_dir), *map(str, args), "--out", str(tmp_path / "x.npz")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("infer: ") and message in err, err
    assert infer_main([str(tmp_path), str(good0), str(good1)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not an export directory" in err
    assert not (tmp_path / "x.npz").exists()


def test_export_cli(checkpoint, tmp_path, capsys):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        base = compose(config_name="export")
        out = tmp_path / "ts"
        chosen = compose(config_name="export", overrides=[f"checkpoint={checkpoint}", "format=pt2", f"out_dir={out}"])
    assert run_export(base) == 2 and "pass checkpoint=" in capsys.readouterr().err
    base.checkpoint = str(tmp_path / "none.ckpt")
    assert run_export(base) == 2 and "none.ckpt: checkpoint not found" in capsys.readouterr().err
    base.checkpoint, base.format = str(checkpoint), "tflite"
    status, err = run_export(base), capsys.readouterr().err
    assert status == 2 and "unknown export format" in err and err.count("\n") == 1
    assert run_export(chosen) == 0
    assert sorted(p.name for p in out.iterdir()) == [FILE_NAMES["pt2"], METADATA_NAME]
    assert json.loads((out / METADATA_NAME).read_text())["files"].keys() == {"pt2"}
    assert f"{out / METADATA_NAME}" in capsys.readouterr().out


@pytest.mark.parametrize("runtime", ["onnxruntime", "openvino"])
def test_cpu_runtimes_keep_the_export_parity(export_dir, expected, pairs, runtime):
    """The engines of fastflow3d.artifact.engines run the same ONNX file to the export's tolerance (1e-4 m), masks
    equal; the default ONNX Predictor on a machine without CUDA runs ONNX Runtime's tuned session."""
    if runtime == "openvino":
        pytest.importorskip("openvino", reason="OpenVINO is an optional extra (icpflow[openvino])")
    from fastflow3d.artifact.engines import cpu_only

    predictor = Predictor.load(export_dir, runtime=runtime, threads=1)
    assert predictor.backend == runtime
    for pair, (flow, valid) in zip(pairs, expected):
        prediction = predictor.predict(pair.pc0, pair.pc1, pair.ego1_from_ego0)
        assert np.array_equal(prediction.in_grid, valid)
        assert np.abs(prediction.flow - flow).max() <= TOLERANCE
    if cpu_only():
        options = Predictor.load(export_dir).network.session.get_session_options()
        assert options.get_session_config_entry("session.intra_op.allow_spinning") == "0"


def crowded_points(seed: int = 1):
    """Two scans of 60,000 and 40,000 points in 150 pillars of the tiny grid (many points per pillar)."""
    rng = np.random.default_rng(seed)
    cells = rng.uniform(-15.0, 15.0, (150, 2))
    scans = []
    for count in (60_000, 40_000):
        xy = cells[rng.integers(0, len(cells), count)] + rng.uniform(-0.05, 0.05, (count, 2))
        scans.append(np.column_stack([xy, rng.uniform(0.3, 2.0, count)]).astype(np.float32))
    return scans


def test_onnx_runtime_pillar_sums_are_exact_with_threads_on_crowded_pillars(export_dir, eager):
    """The pillar means are one scatter-add over many points per pillar: a threaded engine that races on repeated
    pillar ids (ONNX Runtime's ScatterND-add did, issue 33) gives sums that change from run to run. 60,000 points
    in 150 pillars, 2 threads, three runs: each equals eager to the export's tolerance."""
    from fastflow3d.artifact.engines import load_network

    crowded = crowded_points()
    with torch.no_grad():
        want = eager(*map(torch.from_numpy, crowded))[0].numpy()
    network = load_network(export_dir / FILE_NAMES["onnx"], "onnx", runtime="onnxruntime", threads=2)
    for _ in range(3):
        got, valid = network(*crowded)
        assert valid.all() and np.abs(got - want).max() <= TOLERANCE


@pytest.mark.parametrize("file", ["onnx", "int8"])
def test_one_thread_sessions_sum_pillars_with_scatternd_to_the_same_bits(export_dir, int8_export, eager, file):
    """A CPU session of one thread runs the pillar sums as ScatterND-add (fastflow3d.artifact.sequential_scatter):
    every ScatterElements of the export is rewritten, nothing left unread, and the network's output on crowded pillars
    equals the graph as exported on one thread bit for bit (the float one: eager to the export's tolerance). Two
    threads keep the export's scatter (ScatterND races there), as does a machine without the onnx package."""
    import onnx
    import onnxruntime

    from fastflow3d.artifact.engines import load_network, ort_session_options
    from fastflow3d.artifact.file_format import INT8_FILE_NAME
    from fastflow3d.artifact.sequential_scatter import sequential_scatter_sums

    path = export_dir / FILE_NAMES["onnx"] if file == "onnx" else int8_export / INT8_FILE_NAME
    model = onnx.load(str(path))
    before = [node.op_type for node in model.graph.node]
    scatters = before.count("ScatterElements")
    # per scan: the sums of its two means (xyz, embedding) and their counts, one sum shared (the same ids and ones)
    assert scatters == 6 and sequential_scatter_sums(model) == scatters
    ops = [node.op_type for node in model.graph.node]
    assert "ScatterElements" not in ops and ops.count("ScatterND") == scatters
    assert ops.count("Expand") < before.count("Expand")  # the index expansions are gone (none is left unread)
    read = {name for node in model.graph.node for name in node.input} | {out.name for out in model.graph.output}
    assert all(name in read for node in model.graph.node for name in node.output if name)
    assert all(tensor.name in read for tensor in model.graph.initializer)
    onnx.checker.check_model(model)

    points = crowded_points()
    network = load_network(
        path, "onnx", runtime="onnxruntime", threads=1, precision="int8" if file == "int8" else "f32"
    )
    assert network.sequential_scatters == scatters
    exported = onnxruntime.InferenceSession(str(path), ort_session_options(1), providers=["CPUExecutionProvider"])
    want = exported.run(None, {"pc0_compensated": points[0], "pc1": points[1]})
    for _ in range(2):
        got = network(*points)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
    if file == "onnx":
        with torch.no_grad():
            assert np.abs(got[0] - eager(*map(torch.from_numpy, points))[0].numpy()).max() <= TOLERANCE
    assert load_network(path, "onnx", runtime="onnxruntime", threads=2).sequential_scatters == 0


def test_one_thread_rewrite_leaves_other_graphs_and_machines_without_onnx_alone(export_dir, monkeypatch):
    """Only the export's own pillar sums are rewritten: a ScatterElements-add along axis 0, or along axis 1 with
    indices that are not a 1-D tensor expanded over the channels, stays as it is (the model's bytes unchanged); with
    no onnx package the session runs the file as exported."""
    import importlib.util

    import onnxruntime
    from onnx import TensorProto, helper, numpy_helper

    from fastflow3d.artifact.engines import load_network
    from fastflow3d.artifact.sequential_scatter import sequential_scatter_sums

    def graph(axis: int, expanded: bool, rows: int = 4):
        """One ScatterElements-add of ``rows`` rows; ``expanded``: its indices the export's pattern; ``rows`` 1: its
        data a constant (the counts, as ONNX Runtime's optimiser leaves them: the expansion dropped)."""
        ids = helper.make_tensor_value_info("ids", TensorProto.INT64, [rows, 5] if not expanded else [5])
        updates = helper.make_tensor_value_info("updates", TensorProto.FLOAT, [rows, 5])
        out = helper.make_tensor_value_info("out", TensorProto.FLOAT, [rows, 8])
        nodes = [helper.make_node("ScatterElements", ["data", "index", "updates"], ["out"], axis=axis, reduction="add")]
        inputs, initializers = [ids, updates], []
        if rows == 1:
            initializers.append(numpy_helper.from_array(np.zeros((1, 8), np.float32), "data"))
        else:
            inputs.insert(0, helper.make_tensor_value_info("data", TensorProto.FLOAT, [rows, 8]))
        if expanded:
            initializers.append(numpy_helper.from_array(np.array([0]), "zero"))
            nodes.insert(0, helper.make_node("Unsqueeze", ["ids", "zero"], ["index" if rows == 1 else "row"]))
            if rows > 1:
                initializers.append(numpy_helper.from_array(np.array([rows, 5]), "shape"))
                nodes.insert(1, helper.make_node("Expand", ["row", "shape"], ["index"]))
        else:
            nodes[0].input[1] = "ids"
        return helper.make_model(
            helper.make_graph(nodes, "g", inputs, [out], initializers), opset_imports=[helper.make_opsetid("", 18)]
        )

    for axis, expanded in ((0, True), (1, False)):
        model = graph(axis, expanded)
        before = model.SerializeToString()
        assert sequential_scatter_sums(model) == 0 and model.SerializeToString() == before
    unexpanded = graph(1, True)  # indices of one row into data of four: ScatterElements adds into its first row only
    unexpanded.graph.node.remove(unexpanded.graph.node[1])
    unexpanded.graph.node[1].input[1] = "row"
    before = unexpanded.SerializeToString()
    assert sequential_scatter_sums(unexpanded) == 0 and unexpanded.SerializeToString() == before
    counts = graph(1, True, rows=1)
    feed = {"ids": np.array([3, 1, 3, 3, 7]), "updates": np.arange(5, dtype=np.float32)[None]}
    exported = onnxruntime.InferenceSession(counts.SerializeToString(), providers=["CPUExecutionProvider"])
    assert sequential_scatter_sums(counts) == 1
    rewritten = onnxruntime.InferenceSession(counts.SerializeToString(), providers=["CPUExecutionProvider"])
    assert np.array_equal(rewritten.run(None, feed)[0], exported.run(None, feed)[0])

    model = graph(1, True)
    exported = onnxruntime.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    assert sequential_scatter_sums(model) == 1
    ops = [node.op_type for node in model.graph.node]
    assert ops == ["Transpose", "Cast", "Unsqueeze", "Transpose", "ScatterND", "Transpose"]
    rewritten = onnxruntime.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    feed = {"data": rng.normal(size=(4, 8)).astype(np.float32), "ids": np.array([3, 1, 3, 3, 7])}
    feed["updates"] = rng.normal(size=(4, 5)).astype(np.float32)
    assert np.array_equal(rewritten.run(None, feed)[0], exported.run(None, feed)[0])

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "onnx" else find_spec(name, *a))
    assert (
        load_network(export_dir / FILE_NAMES["onnx"], "onnx", runtime="onnxruntime", threads=1).sequential_scatters == 0
    )


def test_the_threads_asked_for_run_the_onnx_network_however_it_is_opened(export_dir, int8_export, monkeypatch):
    """``Predictor.load(..., threads=N)`` (``fastflow3d-infer --threads``, and the stream's one network thread beside
    its own steps) sizes the ONNX Runtime session whether or not a runtime or precision is named, for an export
    directory and a bare ``.onnx`` alike (the directory without ``runtime`` had run on every core, and the stream's
    float32 network on two threads beside its odometry); none given: the usable cores."""
    import fastflow3d.artifact.engines as engines

    monkeypatch.setattr(engines, "available_cores", lambda: 3)
    opened = {
        "directory": {},
        "directory, runtime": {"runtime": "onnxruntime"},
        "directory, int8": {"precision": "int8"},
        "bare .onnx": {"path": export_dir / FILE_NAMES["onnx"]},
    }
    for what, options in opened.items():
        path = options.pop("path", int8_export if options.get("precision") == "int8" else export_dir)
        for threads, want in ((1, 1), (2, 2), (None, 3)):
            session = Predictor.load(path, threads=threads, **options).network.session
            assert session.get_session_options().intra_op_num_threads == want, (what, threads)


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


def test_cpu_runtime_rejects_what_it_cannot_run(export_dir):
    from fastflow3d.artifact.engines import load_network

    with pytest.raises(ArtifactError, match="needs an export directory with ONNX or a .onnx"):
        Predictor.load(export_dir / FILE_NAMES["pt2"], runtime="onnxruntime")
    with pytest.raises(ArtifactError, match="precision 'bf16' is not available with onnxruntime"):
        load_network(export_dir / FILE_NAMES["onnx"], "onnx", runtime="onnxruntime", threads=1, precision="bf16")
    with pytest.raises(ArtifactError, match="unknown runtime 'tensorrt'"):
        load_network(export_dir / FILE_NAMES["onnx"], "onnx", runtime="tensorrt")


# ------------------------------------------------------------------------------------------- the int8 network
@pytest.fixture(scope="module")
def int8_export(checkpoint, tmp_path_factory):
    """The tiny checkpoint exported as ONNX with its int8 network, calibrated on the run's training shards."""
    return export_checkpoint(checkpoint, tmp_path_factory.mktemp("int8") / "export", formats=("onnx",), int8=True)


def test_int8_network_quantises_the_convolutions_and_stays_near_the_float_one(int8_export, checkpoint, pairs):
    """``int8=true`` writes fastflow3d.int8.onnx beside the float32 ONNX: its convolutions read int8 weights (QDQ),
    the rest stays float32; its metadata entry carries its hash and its difference from the float32 network on the
    labelled pairs; the Predictor runs it with precision int8 (and picks ONNX Runtime for it), and its flow on
    pairs it was not calibrated on differs from the float32 flow, but by under INT8_TOLERANCE on average."""
    import onnx

    from fastflow3d.artifact.file_format import INT8, INT8_FILE_NAME
    from fastflow3d.artifact.quantize import INT8_TOLERANCE

    metadata = json.loads((int8_export / METADATA_NAME).read_text())
    entry = metadata["files"][INT8]
    assert entry == {"path": INT8_FILE_NAME, "sha256": sha256_file(int8_export / INT8_FILE_NAME)}
    assert 0 < metadata["int8"]["mean_abs_m"] <= INT8_TOLERANCE and metadata["int8"]["calibration_pairs"] == 1
    assert metadata["int8"]["held_out"] is False  # one labelled pair: the check runs on it too
    graph = onnx.load(str(int8_export / INT8_FILE_NAME)).graph
    convs = [node for node in graph.node if node.op_type == "Conv"]
    weights = {init.name: init for init in graph.initializer}
    produced = {output: node for node in graph.node for output in node.output}
    for conv in convs:  # every convolution's weight is an int8 initializer dequantised on the fly
        dequantise = produced[conv.input[1]]
        assert dequantise.op_type == "DequantizeLinear"
        assert weights[dequantise.input[0]].data_type == onnx.TensorProto.INT8
    assert convs and not any(
        init.data_type == onnx.TensorProto.INT8
        for init in onnx.load(str(int8_export / FILE_NAMES["onnx"])).graph.initializer
    )
    # the float32 network by name: the default, auto, would run the int8 one on a CPU with int8 dot products
    float_predictor = Predictor.load(int8_export, precision="f32")
    int8_predictor = Predictor.load(int8_export, precision="int8")
    assert int8_predictor.backend == "onnxruntime"
    for pair in pairs[1:]:
        want = float_predictor.predict(pair.pc0, pair.pc1, pair.ego1_from_ego0)
        got = int8_predictor.predict(pair.pc0, pair.pc1, pair.ego1_from_ego0)
        assert np.array_equal(got.in_grid, want.in_grid)
        distance = np.linalg.norm(got.flow - want.flow, axis=1)[want.in_grid]
        assert 0 < distance.mean() <= INT8_TOLERANCE and distance.max() > 0


def test_int8_is_refused_in_one_line_where_it_cannot_be_made_or_run(
    int8_export, export_dir, checkpoint, pairs, tmp_path, monkeypatch, capsys
):
    """No shards to calibrate on, a pt2-only export, a network beyond the tolerance (nothing kept: the folder keeps
    its previous export), an export without the int8 network (Predictor and CLI), int8 in OpenVINO: one line each."""
    from fastflow3d.artifact import export as export_module
    from fastflow3d.artifact.engines import load_network
    from fastflow3d.artifact.export import ExportError
    from fastflow3d.artifact.file_format import INT8_FILE_NAME

    with pytest.raises(ExportError, match="int8 calibration needs labelled shards: .*missing.* is not a folder"):
        export_checkpoint(checkpoint, tmp_path / "a", formats=("onnx",), int8=str(tmp_path / "missing"))
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(ArtifactError, match="int8 calibration: .*index.json: no index"):
        export_checkpoint(checkpoint, tmp_path / "a", formats=("onnx",), int8=str(empty))
    with pytest.raises(ExportError, match="int8 quantises the ONNX network: export the onnx format too"):
        export_checkpoint(checkpoint, tmp_path / "a", formats=("pt2",), int8=True)
    out = export_checkpoint(checkpoint, tmp_path / "kept", formats=("onnx",))
    before = {path.name: path.read_bytes() for path in out.iterdir()}
    monkeypatch.setattr(export_module, "INT8_TOLERANCE", 0.0)
    with pytest.raises(ExportError, match=f"{INT8_FILE_NAME}: the int8 network differs .* on average .*not kept"):
        export_checkpoint(checkpoint, out, formats=("onnx",), int8=True)
    assert {path.name: path.read_bytes() for path in out.iterdir()} == before
    assert not any(path.name.startswith(("int8-", ".")) for path in out.parent.iterdir() if path != out)
    with pytest.raises(PredictorError, match="the export has no int8 network; export it with .* int8=true"):
        Predictor.load(export_dir, precision="int8")
    scans = [
        str(write_scan(tmp_path / name, points)) for name, points in (("a.npy", pairs[1].pc0), ("b.npy", pairs[1].pc1))
    ]
    assert infer_main([str(export_dir), *scans, "--precision", "int8", "--out", str(tmp_path / "x.npz")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no int8 network" in err
    with pytest.raises(ArtifactError, match="precision 'int8' is not available with openvino"):
        load_network(int8_export / INT8_FILE_NAME, "onnx", runtime="openvino", threads=1, precision="int8")
    # the export's int8 file given alone as float32: the line says which precisions run it
    y = ["--out", str(tmp_path / "y.npz")]
    assert infer_main([str(int8_export / INT8_FILE_NAME), *scans, *y, "--precision", "f32"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "this is its export's int8 network; run it with precision 'int8' or 'auto'" in err


def test_auto_precision_runs_the_int8_network_only_where_the_export_ships_it_and_the_cpu_has_dot_products(
    int8_export, export_dir, checkpoint, pairs, monkeypatch
):
    """``precision="auto"`` (the default of ``fastflow3d-infer --precision`` and ``eval.py precision=``) runs the
    export's int8 network where it ships one, ONNX Runtime runs it on the CPU and the CPU has int8 dot products; in
    every other case float32: an export without int8, a CPU without them, another format or runtime, ONNX Runtime
    with its CUDA provider, a checkpoint. A bare int8 ``.onnx`` runs as int8 (no other way). What ran is
    ``Predictor.precision``, and its flow is that precision's, bit for bit."""
    from fastflow3d.artifact.file_format import INT8_FILE_NAME
    from fastflow3d.inference import model_loading

    pair = pairs[0]

    def flow(predictor):
        return predictor(pair.pc0, pair.pc1, pair.ego1_from_ego0)

    int8_flow, f32_flow = (flow(Predictor.load(int8_export, precision=p)) for p in ("int8", "f32"))
    assert not np.array_equal(int8_flow, f32_flow)
    for dot_products, want in ((True, "int8"), (False, "f32")):
        monkeypatch.setattr(model_loading, "int8_dot_products", lambda answer=dot_products: answer)
        predictor = Predictor.load(int8_export, precision="auto")
        assert predictor.precision == want
        assert np.array_equal(flow(predictor), int8_flow if want == "int8" else f32_flow)
    monkeypatch.setattr(model_loading, "int8_dot_products", lambda: True)
    float_only = {
        "no int8 in the export": (export_dir, None, None),
        "another format": (int8_export, "pt2", None),
        "another runtime": (int8_export, None, "openvino"),
        "the float32 .onnx alone": (int8_export / FILE_NAMES["onnx"], None, None),
        "a checkpoint": (checkpoint, None, None),
        "no such path": (int8_export / "missing", None, None),
    }
    for what, (path, backend, runtime) in float_only.items():
        assert model_loading.auto_precision(Path(path), backend, runtime) == "f32", what
    assert Predictor.load(export_dir, precision="auto").precision == "f32"
    assert Predictor.load(checkpoint, precision="auto").precision == "f32"
    assert model_loading.auto_precision(int8_export, None, "onnxruntime") == "int8"
    bare = Predictor.load(int8_export / INT8_FILE_NAME, precision="auto")
    assert bare.precision == "int8" and np.array_equal(flow(bare), int8_flow)
    monkeypatch.setattr(model_loading, "cpu_only", lambda: False)  # ONNX Runtime would run on its CUDA provider
    assert model_loading.auto_precision(int8_export, None, None) == "f32"
    assert model_loading.auto_precision(int8_export, None, "onnxruntime") == "int8"  # the CPU session, named


def test_the_cli_runs_auto_precision_by_default_and_says_which(int8_export, pairs, tmp_path, monkeypatch, capsys):
    """``fastflow3d-infer EXPORT ...`` without ``--precision`` runs ``auto``'s network, names it on its last line,
    and a stream's manifest records it (its flows are that network's)."""
    from fastflow3d.inference import model_loading

    monkeypatch.setattr(model_loading, "int8_dot_products", lambda: True)
    scans = tmp_path / "scans"
    scans.mkdir()
    for k, points in enumerate((pairs[1].pc0, pairs[1].pc1, pairs[2].pc1)):
        write_scan(scans / f"{k}.npy", points)
    pair_out = tmp_path / "pair.npz"
    assert (
        infer_main([str(int8_export), str(scans / "0.npy"), str(scans / "1.npy"), "--out", str(pair_out), "--no-bev"])
        == 0
    )
    assert capsys.readouterr().out.rstrip().endswith("(int8 network)")
    want = Predictor.load(int8_export, precision="int8")(pairs[1].pc0, pairs[1].pc1).astype(np.float32)
    assert np.array_equal(np.load(pair_out)["flow"], want)
    assert infer_main([str(int8_export), str(scans), "--out", str(tmp_path / "stream")]) == 0
    assert capsys.readouterr().out.rstrip().endswith("(int8 network)")
    manifest = json.loads((tmp_path / "stream" / "stream.json").read_text())
    assert manifest["options"]["precision"] == "int8"
    monkeypatch.setattr(model_loading, "int8_dot_products", lambda: False)
    assert infer_main([str(int8_export), str(scans), "--out", str(tmp_path / "stream_f32")]) == 0
    assert capsys.readouterr().out.rstrip().endswith("(f32 network)")
    assert "precision" not in json.loads((tmp_path / "stream_f32" / "stream.json").read_text())["options"]
    # the float32 run's folder is not replaced by the int8 one's flows, and the line says why
    monkeypatch.setattr(model_loading, "int8_dot_products", lambda: True)
    assert infer_main([str(int8_export), str(scans), "--out", str(tmp_path / "stream_f32")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "this stream's flows made with other options (precision f32, now int8)" in err


def test_int8_asked_for_on_a_cpu_without_dot_products_says_its_cost(int8_export, pairs, tmp_path, monkeypatch, capsys):
    """``--precision int8`` where the CPU has no int8 dot products runs as asked, with one line saying what it costs;
    ``auto`` there runs f32 and says nothing; bf16 without native bf16 is said the same way."""
    from fastflow3d.inference import model_loading
    from fastflow3d.inference.prediction import PredictorWarning

    monkeypatch.setattr(model_loading, "int8_dot_products", lambda: False)
    with pytest.warns(PredictorWarning, match="precision int8 on a CPU without int8 dot products"):
        assert Predictor.load(int8_export, precision="int8").precision == "int8"
    with warnings.catch_warnings():
        warnings.simplefilter("error", PredictorWarning)
        assert Predictor.load(int8_export, precision="auto").precision == "f32"
    scans = tmp_path / "scans"
    scans.mkdir()
    for k, points in enumerate((pairs[1].pc0, pairs[1].pc1)):
        write_scan(scans / f"{k}.npy", points)
    args = [str(int8_export), str(scans / "0.npy"), str(scans / "1.npy"), "--no-bev", "--precision", "int8"]
    assert infer_main([*args, "--out", str(tmp_path / "pair.npz")]) == 0
    err = capsys.readouterr().err.splitlines()
    assert [line for line in err if "dot products" in line] == [
        "infer: warning: " + model_loading.precision_cost("int8")
    ]
    monkeypatch.setattr("icpflow.core.hardware.native_bf16", lambda: (False, "this CPU has no bf16 instructions"))
    assert model_loading.precision_cost("bf16").startswith("precision bf16: this CPU has no bf16 instructions")
    monkeypatch.setattr(model_loading, "int8_dot_products", lambda: True)
    assert model_loading.precision_cost("int8") is None and model_loading.precision_cost("f32") is None


def test_int8_dot_products_are_read_from_the_cpus_flags():
    """``engines.int8_dot_products``: x86 AVX512-VNNI or AVX-VNNI, Arm's asimddp (``/proc/cpuinfo``); an Apple
    Silicon Mac has them; elsewhere (no cpuinfo) they are not assumed."""
    from fastflow3d.artifact.engines import int8_dot_products

    def x86(flags):
        first = f"processor\t: 0\nmodel name\t: some CPU\nflags\t\t: fpu sse2 {flags}\n"
        return first + "\nprocessor\t: 1\nflags\t: avx512_vnni\n"

    assert int8_dot_products(x86("avx2 avx512f avx512_vnni"))
    assert int8_dot_products(x86("avx2 avx_vnni"))
    assert not int8_dot_products(x86("avx2 avx512f avx512bw"))  # the second processor's flags are not read
    assert int8_dot_products("processor\t: 0\nFeatures\t: fp asimd asimdrdm asimddp\n")
    assert not int8_dot_products("processor\t: 0\nFeatures\t: fp asimd\n")
    assert int8_dot_products("", system="Darwin", machine="arm64")
    assert not int8_dot_products("", system="Darwin", machine="x86_64")
    assert not int8_dot_products("", system="Windows", machine="AMD64")


def test_eval_scores_the_int8_network(int8_export, pairs):
    """``eval.py precision=int8``: the student methods run the export's int8 network (the Predictor's)."""
    from omegaconf import OmegaConf

    from fastflow3d.inference.eval_methods import refined_streamed_student_method, student_method

    cfg = OmegaConf.create({"checkpoint": str(int8_export), "precision": "int8", "sensor_height": None})
    want = Predictor.load(int8_export, precision="int8")(pairs[0].pc0, pairs[0].pc1, pairs[0].ego1_from_ego0)
    assert np.array_equal(student_method(cfg)(pairs[0], 0), want)
    assert refined_streamed_student_method(cfg).predictor.network.session._model_path.endswith("int8.onnx")
    assert student_method(cfg).description == "int8 network, onnxruntime"


# ------------------------------------------------------------------------------------- height frame, bare files
def lowered(pair, height: float):
    """pc0, pc1 and ego1_from_ego0 of ``pair`` as a sensor ``height`` m above its ground would give them (the
    KITTI velodyne convention: ground near z = -height)."""
    return lift_points(pair.pc0, -height), lift_points(pair.pc1, -height), lift_transform(pair.ego1_from_ego0, -height)


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


def test_older_export_metadata_still_loads(ground_checkpoint, ground_export, pairs, tmp_path):
    """metadata.json of an older version (``preprocessing: {remove_ground, teacher: ICPFlowConfig fields}``) reads
    as the typed block, in the synthetic frame it was trained in, and predicts as the current form does."""
    path, teacher = ground_checkpoint
    current = tmp_path / "current"
    current.mkdir()
    for name in (METADATA_NAME, FILE_NAMES["pt2"]):
        (current / name).write_bytes((ground_export / name).read_bytes())
    metadata = json.loads((current / METADATA_NAME).read_text())
    del metadata["input"], metadata["input_note"]
    metadata["metadata_version"] = 1
    metadata["preprocessing"] = {
        "remove_ground": True,
        "teacher": dict(LEGACY_TEACHER),
        "note": "older form",
    }
    (current / METADATA_NAME).write_text(json.dumps(metadata))
    old = Predictor.load(current)
    assert old.remove_ground and old.preprocessing == Preprocessing.from_teacher(teacher)
    assert old.contract.grid == upgrade(json.loads((ground_export / METADATA_NAME).read_text())).grid
    # exports older than ground removal had no preprocessing entry: every point, the synthetic frame
    oldest = upgrade({key: value for key, value in metadata.items() if key != "preprocessing"})
    assert not oldest.remove_ground and oldest.preprocessing.frame.ground_z == 0.0
    with pytest.raises(ContractError, match="says nothing about ground removal"):
        upgrade({})
    assert old.preprocessing.frame.ground_z == 0.0 and old.preprocessing.patchwork_z_offset == -1.9
    pair = pairs[0]
    new = Predictor.load(path).predict(pair.pc0, pair.pc1, pair.ego1_from_ego0)
    again = old.predict(pair.pc0, pair.pc1, pair.ego1_from_ego0)
    assert np.array_equal(new.ground0, again.ground0) and np.abs(new.flow - again.flow).max() <= TOLERANCE


def test_bare_export_without_metadata_is_refused_unless_told(ground_export, pairs, tmp_path, capsys):
    """A ``.pt2`` without its metadata.json would run with ground removal off: refused (Predictor and CLI, one
    line), and runs as its export does once told what the metadata says (--metadata, preprocessing=)."""
    export = ground_export
    bare = tmp_path / "bare" / "model.pt2"
    bare.parent.mkdir()
    bare.write_bytes((export / FILE_NAMES["pt2"]).read_bytes())
    with pytest.raises(PredictorError, match="no metadata.json beside it describes this file") as error:
        Predictor.load(bare)
    assert "\n" not in str(error.value)
    pair = pairs[0]
    reference = Predictor.load(export).predict(pair.pc0, pair.pc1, pair.ego1_from_ego0)
    told = Predictor.load(bare, preprocessing=export / METADATA_NAME)
    assert told.remove_ground and told.preprocessing.ground.sensor_height == 1.9
    assert np.abs(told(pair.pc0, pair.pc1, pair.ego1_from_ego0) - reference.flow).max() <= TOLERANCE
    every = Predictor.load(bare, preprocessing={"remove_ground": False})
    assert not every.remove_ground
    scan0, scan1 = write_scan(tmp_path / "a.npy", pair.pc0), write_scan(tmp_path / "b.npy", pair.pc1)
    poses, out = write_poses(tmp_path / "poses.txt", [pair.pose0, pair.pose1]), tmp_path / "flow.npz"
    common = [str(bare), str(scan0), str(scan1), "--poses", str(poses), "--out", str(out), "--no-bev"]
    assert infer_main(common) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no metadata.json beside it" in err and "--metadata FILE" in err
    assert not out.exists()
    assert infer_main([*common, "--metadata", str(export / METADATA_NAME)]) == 0
    with np.load(out) as result:
        assert np.array_equal(result["ground0"], reference.ground0)
        assert np.abs(result["flow"] - reference.flow).max() <= TOLERANCE
    assert infer_main([*common, "--remove-ground", "no"]) == 0
    with np.load(out) as result:
        assert not result["ground0"].any()


def test_infer_cli_sensor_height(export_dir, pairs, expected, tmp_path, capsys):
    """--sensor-height 1.73 reads scans in a sensor frame; without it the CLI lifts them and says so in one line."""
    pair, (flow, _) = pairs[0], expected[0]
    pc0, pc1, ego = lowered(pair, 1.73)
    scan0, scan1 = write_scan(tmp_path / "a.npy", pc0), write_scan(tmp_path / "b.npy", pc1)
    transform = tmp_path / "ego.npy"
    np.save(transform, ego)
    out = tmp_path / "flow.npz"
    common = [str(export_dir), str(scan0), str(scan1), "--ego", str(transform), "--out", str(out), "--no-bev"]
    assert infer_main([*common, "--sensor-height", "1.73"]) == 0
    assert "warning: the ground" not in capsys.readouterr().err
    with np.load(out) as result:
        assert np.abs(result["flow"] - flow).max() <= 1e-3
    assert infer_main(common) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if "ground of pc0" in line]
    assert len(lines) == 1 and lines[0].startswith("infer: warning: the ground of pc0 lies at z = -1.")
    with pytest.raises(SystemExit):
        infer_main([*common, "--sensor-height", "tall"])


@pytest.mark.slow
def test_model_options_export_with_parity_and_the_predictor_runs_them(pairs, tmp_path):
    """The network's options beyond ZeroFlow's, all in one network (DeFlow's GRU decoder; the cost volume at two
    levels; the centroid shift at two windows): the export keeps parity and the Predictor and the CLI run it."""
    options = {
        "decoder": "gru",
        "gru_iterations": 2,
        "gru_channels": 8,
        "correlation_levels": [0, 2],
        "correlation_radius": 2,
        "motion_windows": [1, 3],
    }
    pair = pairs[0]
    near0 = np.flatnonzero(np.abs(pair.pc0[:, :2]).max(axis=1) < NEAR)[:3000]
    near1 = np.flatnonzero(np.abs(pair.pc1[:, :2]).max(axis=1) < NEAR)[:3000]
    checkpoint = tiny_checkpoint(tmp_path / "variant.ckpt", pair, 5, near0, near1, options=options)
    out_dir = export_checkpoint(checkpoint)
    metadata = json.loads((out_dir / METADATA_NAME).read_text())
    assert all(metadata["model"][key] == value for key, value in options.items())
    assert max(metadata["parity_max_abs_m"].values()) <= TOLERANCE
    flow, valid = eager_full_flow(SingleSampleNet(load_student(checkpoint)[0]).eval(), pairs[1])
    for backend in ("onnx", "pt2"):
        prediction = Predictor.load(out_dir, backend=backend).predict(
            pairs[1].pc0, pairs[1].pc1, pairs[1].ego1_from_ego0
        )
        assert np.array_equal(prediction.in_grid, valid) and np.abs(prediction.flow - flow).max() <= TOLERANCE
    # the inference CLI on raw scan files with poses
    poses = write_poses(tmp_path / "poses.txt", [pairs[1].pose0, pairs[1].pose1])
    scan0, scan1 = write_scan(tmp_path / "a.npy", pairs[1].pc0), write_scan(tmp_path / "b.npy", pairs[1].pc1)
    out = tmp_path / "flow.npz"
    assert infer_main([str(out_dir), str(scan0), str(scan1), "--poses", str(poses), "--out", str(out), "--no-bev"]) == 0
    with np.load(out) as result:
        assert np.abs(result["flow"] - flow).max() <= TOLERANCE


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
