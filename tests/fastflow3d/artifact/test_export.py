"""Export (ONNX, torch.export) parity with eager on every CPU engine, the metadata, older TorchScript exports and
export metadata, bare exports, and export.py. The tiny exported model: ``tests/fastflow3d/conftest.py``."""

import json
import warnings

import numpy as np
import pytest
import torch

from fastflow3d.artifact.checkpoint import load_student
from fastflow3d.artifact.export import export_checkpoint, run_export
from fastflow3d.artifact.file_format import FILE_NAMES, METADATA_NAME, ArtifactError, SingleSampleNet, sha256_file
from fastflow3d.inference.cli import main as infer_main
from fastflow3d.inference.prediction import PredictorError
from fastflow3d.inference.predictor import Predictor
from fastflow3d.network.contract import ContractError, upgrade
from fastflow3d.network.voxelize import Grid
from icpflow import __version__
from icpflow.core.geometry import ego_flow
from icpflow.scans.preprocess import Preprocessing

from helpers.data import REPO
from helpers.exports import (
    LEGACY_TEACHER,
    NEAR,
    TOLERANCE,
    crowded_points,
    eager_full_flow,
    write_poses,
    write_scan,
)
from helpers.students import tiny_checkpoint  # tests/ is on sys.path (pytest prepend import mode)
from helpers.training import TINY_MODEL

pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript")


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


def test_cpu_runtime_rejects_what_it_cannot_run(export_dir):
    from fastflow3d.artifact.engines import load_network

    with pytest.raises(ArtifactError, match="needs an export directory with ONNX or a .onnx"):
        Predictor.load(export_dir / FILE_NAMES["pt2"], runtime="onnxruntime")
    with pytest.raises(ArtifactError, match="precision 'bf16' is not available with onnxruntime"):
        load_network(export_dir / FILE_NAMES["onnx"], "onnx", runtime="onnxruntime", threads=1, precision="bf16")
    with pytest.raises(ArtifactError, match="unknown runtime 'tensorrt'"):
        load_network(export_dir / FILE_NAMES["onnx"], "onnx", runtime="tensorrt")


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


def test_a_checkpoint_and_out_dir_with_a_tilde_are_the_home_folders(tmp_path, monkeypatch, tiny_student, capsys):
    """``export.py checkpoint='~/...' out_dir='~/...'``: ``~`` is the home folder, as in every path option (no
    literal ``~`` folder)."""
    from omegaconf import OmegaConf

    from fastflow3d.artifact.export import run_export

    monkeypatch.setenv("HOME", str(tmp_path))
    (tmp_path / "student.ckpt").symlink_to(tiny_student)
    cfg = {"checkpoint": "~/student.ckpt", "out_dir": "~/export", "format": "pt2", "int8": False}
    assert run_export(OmegaConf.create(cfg)) == 0, capsys.readouterr().err
    assert (tmp_path / "export" / "fastflow3d.pt2").is_file() and not (tmp_path / "~").exists()
    assert run_export(OmegaConf.create({**cfg, "checkpoint": "~/none.ckpt"})) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == f"export: {tmp_path / 'none.ckpt'}: checkpoint not found"
