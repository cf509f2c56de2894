"""The int8 network of an export: its quantised convolutions near the float one, refused in one line where it
cannot be made or run, chosen by ``auto`` only where the export ships it and the CPU has int8 dot products (the CLI
says which), scored by eval.py."""

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from fastflow3d.artifact.export import export_checkpoint
from fastflow3d.artifact.file_format import FILE_NAMES, METADATA_NAME, ArtifactError, sha256_file
from fastflow3d.inference.cli import main as infer_main
from fastflow3d.inference.prediction import PredictorError, PredictorWarning
from fastflow3d.inference.predictor import Predictor

from helpers.exports import (
    write_scan,
)

pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript")


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


def test_int8_asked_for_on_a_cpu_without_dot_products_says_its_cost(int8_export, pairs, tmp_path, monkeypatch, capsys):
    """``--precision int8`` where the CPU has no int8 dot products runs as asked, with one line saying what it costs;
    ``auto`` there runs f32 and says nothing; bf16 without native bf16 is said the same way."""
    from fastflow3d.inference import model_loading

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
