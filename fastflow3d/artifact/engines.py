"""Which engine runs a model file, and the one place a model file is opened (:func:`load_network`).

Every engine gives a network with the artifact's calling convention (``fastflow3d.artifact.file_format``:
``(pc0_compensated (N0, 3), pc1 (N1, 3)) float32 numpy -> (residual (N0, 3) float32, valid (N0,) bool)``):

* ``.onnx`` in ONNX Runtime (:class:`OnnxRuntimeNetwork`): its default session (CUDA provider first where installed),
  or, ``runtime="onnxruntime"``, the tuned CPU session: every graph optimisation, ``threads`` intra-op threads,
  sequential execution and no spin-waiting of idle threads (spinning threads compete with the rest of the process,
  and with other processes, for the cores of a small machine); on one thread, its pillar sums as one-thread
  ``ScatterND`` (``fastflow3d.artifact.sequential_scatter``: the same sums, the int8 network 1.4x quicker);
* ``.onnx`` in Intel OpenVINO (``runtime="openvino"``, :class:`OpenVinoNetwork`, ``pip install 'icpflow[openvino]'``),
  compiled for the CPU with a latency hint and ``threads`` inference threads; ``precision="bf16"`` runs in bfloat16
  where the CPU has it (AVX512-BF16 / AMX), else OpenVINO keeps float32;
* ``.pt2`` (``torch.export``, checked by ``fastflow3d.artifact.safe_loading`` first), a legacy TorchScript ``.pt`` and
  a training checkpoint (``.ckpt``, eager) in PyTorch on a device (:class:`TorchNetwork`).

``precision`` is ``f32``, ``bf16`` (OpenVINO only) or ``int8`` (ONNX Runtime, on the export's ``fastflow3d.int8.onnx``,
``fastflow3d.artifact.quantize``, which ``fastflow3d.inference.model_loading`` picks). Every float runtime is checked
against eager PyTorch by ``fastflow3d.artifact.export.measure_parity`` in ``tests/fastflow3d/artifact/test_export.py``
and in ``benchmarks/bench_student_latency.py``: float32 within the export's ``PARITY_TOLERANCE`` (1e-4 m), bf16 within
:data:`BF16_TOLERANCE`; the int8 network against the float32 one, at export, on labelled pairs (``INT8_TOLERANCE``
on average). The Predictor, the export's parity check and the latency benchmark open their files here.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import torch
from torch.export.passes import move_to_device_pass

from fastflow3d.artifact.checkpoint import load_student
from fastflow3d.artifact.file_format import INPUT_NAMES, LEGACY_FORMATS, OUTPUT_NAMES, ArtifactError, SingleSampleNet
from fastflow3d.artifact.safe_loading import TORCHSCRIPT_WARNING, check_pt2
from icpflow.core.errors_and_signals import one_line
from icpflow.core.stops import raise_stop_behind
from icpflow.core.threads import available_cores, cpu_fields

RUNTIMES = ("onnxruntime", "openvino")
PRECISIONS = ("f32", "bf16", "int8")
#: the one runtime that runs each reduced precision (f32 runs in any)
PRECISION_RUNTIMES = {"bf16": "openvino", "int8": "onnxruntime"}
#: metres; bfloat16 keeps 8 bits of mantissa, so a residual of a few metres is off by up to about 2 cm
BF16_TOLERANCE = 0.05


#: CPU features (``/proc/cpuinfo`` flags) with which ONNX Runtime multiplies uint8 by int8 in dot products of its
#: own: x86 AVX512-VNNI and AVX-VNNI (without them it uses VPMADDUBSW, whose 16-bit sums can saturate: ONNX Runtime's
#: quantisation guide), Arm's dot product (``asimddp``)
INT8_DOT_PRODUCTS = ("avx512_vnni", "avx_vnni", "asimddp")


def int8_dot_products(cpuinfo: str | None = None, system: str | None = None, machine: str | None = None) -> bool:
    """Does this CPU run the int8 network's convolutions in int8 dot products (:data:`INT8_DOT_PRODUCTS`), where they
    are about twice as quick as float32 and exact? On Linux from ``cpuinfo`` (``/proc/cpuinfo``'s text, read when
    None); an Apple Silicon Mac has them (``system`` / ``machine``: ``platform.system()`` / ``platform.machine()``
    when None); elsewhere unknown, so False."""
    import platform

    fields = cpu_fields(cpuinfo)
    if fields:
        flags = set((fields.get("flags") or fields.get("Features") or "").split())
        return any(flag in flags for flag in INT8_DOT_PRODUCTS)
    return (system or platform.system()) == "Darwin" and (machine or platform.machine()) == "arm64"


def cpu_only() -> bool:
    """True when ONNX Runtime has no CUDA provider here (then ``Predictor`` runs ONNX with the tuned CPU session)."""
    import onnxruntime

    return "CUDAExecutionProvider" not in onnxruntime.get_available_providers()


def ort_session_options(threads: int):
    """ONNX Runtime ``SessionOptions``: all graph optimisations, ``threads`` intra-op threads, one inter-op
    thread, sequential execution, idle threads not spinning."""
    import onnxruntime

    options = onnxruntime.SessionOptions()
    options.graph_optimization_level = onnxruntime.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.execution_mode = onnxruntime.ExecutionMode.ORT_SEQUENTIAL
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.add_session_config_entry("session.inter_op.allow_spinning", "0")
    return options


class OpenVinoNetwork:
    """An exported ``.onnx`` compiled by OpenVINO for the CPU: numpy in, numpy out (see the module docstring)."""

    def __init__(self, path: Path, threads: int, precision: str = "f32"):
        try:
            import openvino
        except ImportError as error:
            raise_stop_behind(error)
            raise ArtifactError(
                f"{path}: the openvino runtime needs openvino (pip install 'icpflow[openvino]')"
            ) from None
        core = openvino.Core()
        config = {
            "PERFORMANCE_HINT": "LATENCY",
            "INFERENCE_NUM_THREADS": threads,
            "INFERENCE_PRECISION_HINT": "bf16" if precision == "bf16" else "f32",
        }
        try:
            self.compiled = core.compile_model(core.read_model(str(path)), "CPU", config)
        except Exception as error:  # OpenVINO raises its own exception types for damaged or foreign files
            raise_stop_behind(error)
            raise ArtifactError(f"{path}: OpenVINO cannot compile it: {one_line(error)[:300]}") from None
        names = tuple(port.get_any_name() for port in self.compiled.inputs)
        if names != INPUT_NAMES:
            raise ArtifactError(f"{path}: ONNX inputs are {names}, expected {INPUT_NAMES} (not a FastFlow3D export)")
        self.request = self.compiled.create_infer_request()
        self.outputs = [self.compiled.output(name) for name in OUTPUT_NAMES]

    def __call__(self, pc0_compensated: np.ndarray, pc1: np.ndarray):
        results = self.request.infer({INPUT_NAMES[0]: pc0_compensated, INPUT_NAMES[1]: pc1})
        residual, valid = (results[port] for port in self.outputs)
        return np.asarray(residual, np.float32), np.asarray(valid, bool)


class OnnxRuntimeNetwork:
    """An exported ``.onnx`` in ONNX Runtime: ``(pc0_compensated, pc1) -> (residual, valid)`` numpy arrays."""

    def __init__(self, path: Path, providers=None, options=None):
        """``options``: an ``onnxruntime.SessionOptions`` (:func:`ort_session_options`), or None for
        ONNX Runtime's defaults. A CPU session of one intra-op thread runs the graph with its pillar sums rewritten
        for one thread (``fastflow3d.artifact.sequential_scatter``; where the ``onnx`` package is installed)."""
        try:
            import onnxruntime
        except ImportError as error:
            raise_stop_behind(error)
            raise ArtifactError(f"{path}: running .onnx needs onnxruntime (pip install 'icpflow[export]')") from None
        available = onnxruntime.get_available_providers()
        if providers is None:
            providers = [name for name in ("CUDAExecutionProvider", "CPUExecutionProvider") if name in available]
        #: how many pillar sums run as one-thread ScatterND (0: the graph as exported)
        self.sequential_scatters = 0
        try:
            model = str(path)
            if (
                options is not None
                and options.intra_op_num_threads == 1
                and list(providers) == ["CPUExecutionProvider"]
            ):
                model = self._one_thread_graph(path)
            self.session = onnxruntime.InferenceSession(model, options, providers=list(providers))
        except Exception as error:  # onnx and onnxruntime raise their own exception types for damaged or foreign files
            raise_stop_behind(error)
            raise ArtifactError(f"{path}: cannot load ONNX model: {one_line(error)}") from None
        names = tuple(entry.name for entry in self.session.get_inputs())
        if names != INPUT_NAMES:
            raise ArtifactError(f"{path}: ONNX inputs are {names}, expected {INPUT_NAMES} (not a FastFlow3D export)")

    def _one_thread_graph(self, path: Path):
        """The file's graph with its pillar sums rewritten for one thread (serialised), or its path where nothing
        was rewritten or the ``onnx`` package is missing."""
        if importlib.util.find_spec("onnx") is None:
            return str(path)
        import onnx

        from fastflow3d.artifact.sequential_scatter import sequential_scatter_sums

        graph = onnx.load(str(path))
        self.sequential_scatters = sequential_scatter_sums(graph)
        return graph.SerializeToString() if self.sequential_scatters else str(path)

    def __call__(self, pc0_compensated: np.ndarray, pc1: np.ndarray):
        residual, valid = self.session.run(list(OUTPUT_NAMES), {INPUT_NAMES[0]: pc0_compensated, INPUT_NAMES[1]: pc1})
        return residual, valid


class TorchNetwork:
    """A :class:`SingleSampleNet`, a loaded ExportedProgram's module or a TorchScript trace on ``device``: numpy in,
    numpy out (float32 residual). ``bf16``: the module runs under bfloat16 autocast (the points stay float32);
    ``config``: the training config of the checkpoint it was opened from (None for other files)."""

    def __init__(self, module, device: str = "cpu", bf16: bool = False, config: dict | None = None):
        self.module, self.device, self.bf16, self.config = module, torch.device(device), bool(bf16), config

    def __call__(self, pc0_compensated: np.ndarray, pc1: np.ndarray):
        with torch.inference_mode(), torch.autocast(self.device.type, torch.bfloat16, enabled=self.bf16):
            residual, valid = self.module(
                torch.from_numpy(pc0_compensated).to(self.device), torch.from_numpy(pc1).to(self.device)
            )
        return residual.float().cpu().numpy(), valid.cpu().numpy()


def choose_format(files: dict, where: Path) -> str:
    """ONNX when the export has it and onnxruntime is installed (or there is nothing else), else ``pt2``. Never
    the legacy TorchScript: an export with only that is refused (one line) unless the caller names the backend."""
    others = [kind for kind in ("pt2",) if kind in files]
    if "onnx" in files and (not others or importlib.util.find_spec("onnxruntime") is not None):
        return "onnx"
    if others:
        return others[0]
    if any(kind in files for kind in LEGACY_FORMATS):
        raise ArtifactError(f"{where}: the export holds only TorchScript; {TORCHSCRIPT_WARNING}")
    return "onnx"


def _runtime_network(path: Path, runtime: str, threads: int | None, precision: str):
    """The network of the ``.onnx`` at ``path`` in ``runtime`` (see the module docstring)."""
    if runtime not in RUNTIMES:
        raise ArtifactError(f"{path}: unknown runtime {runtime!r}; use one of {', '.join(RUNTIMES)}")
    wanted = PRECISION_RUNTIMES.get(precision, runtime)
    if precision not in PRECISIONS or runtime != wanted:
        raise ArtifactError(
            f"{path}: precision {precision!r} is not available with {runtime} (f32; bf16: openvino; int8: onnxruntime)"
        )
    threads = threads or available_cores()
    if runtime == "openvino":
        return OpenVinoNetwork(path, threads, precision)
    return OnnxRuntimeNetwork(path, ["CPUExecutionProvider"], ort_session_options(threads))


def load_network(
    path: Path,
    kind: str,
    device: str = "cpu",
    runtime: str | None = None,
    threads: int | None = None,
    precision: str = "f32",
    providers=None,
):
    """The runnable network (numpy in, numpy out) of one model file of format ``kind``: the one place model files
    are opened, in any engine (module docstring).

    ``kind``: ``onnx``; ``pt2`` (passes :func:`~fastflow3d.artifact.safe_loading.check_pt2` first); ``torchscript``
    (legacy ``.pt``: it can run code when loaded, so it is only read when the caller asked for it by name, see
    :func:`choose_format`); ``checkpoint`` (a training ``.ckpt``, ``fastflow3d.artifact.checkpoint.load_student``:
    eager PyTorch; the network's ``module.model`` is the FastFlow3D and ``config`` its training config).
    ONNX: ``runtime`` ``onnxruntime`` (the tuned CPU session) or ``openvino`` with ``threads`` (default: the usable
    cores) and ``precision``; ``providers``: ONNX Runtime's default session with these execution providers; neither:
    the default session where ONNX Runtime has its CUDA provider, else the tuned CPU session (same numbers, 1.3 to
    1.4x faster on 2 cores; BENCHMARKS.md). ``device`` applies to the PyTorch formats and checkpoints."""
    if kind == "onnx":
        if runtime is None and providers is None and cpu_only():
            runtime = "onnxruntime"
        if runtime is not None:
            return _runtime_network(path, runtime, threads, precision)
        return OnnxRuntimeNetwork(path, providers)
    if kind == "checkpoint":
        model, config = load_student(path, map_location=device)
        return TorchNetwork(SingleSampleNet(model).eval(), device, config=config)
    if kind == "pt2":
        check_pt2(path)
    try:
        if kind == "pt2":
            program = torch.export.load(str(path))
            if torch.device(device).type != "cpu":  # exported on the CPU; not yet checked on a GPU
                program = move_to_device_pass(program, device)
            module = program.module()
        else:  # legacy TorchScript exports (torch.jit is deprecated; read while older exports are in use)
            module = torch.jit.load(str(path), map_location=device).eval()
    except Exception as error:  # damaged or foreign files raise many types (RuntimeError, zipfile, pickle errors)
        raise_stop_behind(error)
        raise ArtifactError(f"{path}: cannot load {kind}: {one_line(error)[:300]}") from None
    return TorchNetwork(module, device)
