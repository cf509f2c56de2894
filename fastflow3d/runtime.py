"""CPU inference backends for an exported FastFlow3D (``fastflow3d.onnx``): which engine runs it and how.

``runtime_network(path, runtime, threads, precision)`` gives a network with the artifact's calling convention
(``(pc0_compensated (N0, 3), pc1 (N1, 3)) float32 -> (residual (N0, 3) float32, valid (N0,) bool)``):

* ``onnxruntime``: ONNX Runtime with every graph optimisation, ``threads`` intra-op threads, sequential execution
  and no spin-waiting of idle threads (spinning threads compete with the rest of the process, and with other
  processes, for the cores of a small machine);
* ``openvino``: Intel OpenVINO (``pip install 'icpflow[openvino]'``) reading the same ``.onnx``, compiled for the
  CPU with a latency hint and ``threads`` inference threads; ``precision="bf16"`` runs in bfloat16 where the CPU
  has it (AVX512-BF16 / AMX), else OpenVINO keeps float32.

``precision`` is ``f32`` or ``bf16`` (OpenVINO only). Every runtime is checked against eager PyTorch by
``fastflow3d.export.measure_parity`` in ``tests/test_export.py`` and in ``benchmarks/bench_student_latency.py``: float32
within the export's ``PARITY_TOLERANCE`` (1e-4 m), bf16 within :data:`BF16_TOLERANCE`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from fastflow3d.artifact import INPUT_NAMES, OUTPUT_NAMES, ArtifactError, OnnxRuntimeNetwork
from icpflow.entry import one_line

RUNTIMES = ("onnxruntime", "openvino")
PRECISIONS = ("f32", "bf16")
#: metres; bfloat16 keeps 8 bits of mantissa, so a residual of a few metres is off by up to about 2 cm
BF16_TOLERANCE = 0.05


def default_threads() -> int:
    """The cores this process may use (``os.sched_getaffinity`` where the OS has it)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - macOS, Windows
        return max(1, os.cpu_count() or 1)


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
        except ImportError:
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


def runtime_network(path: Path, runtime: str = "onnxruntime", threads: int | None = None, precision: str = "f32"):
    """The network of the ``.onnx`` at ``path`` in ``runtime`` (see the module docstring)."""
    if runtime not in RUNTIMES:
        raise ArtifactError(f"{path}: unknown runtime {runtime!r}; use one of {', '.join(RUNTIMES)}")
    if precision not in PRECISIONS or (precision == "bf16" and runtime != "openvino"):
        raise ArtifactError(f"{path}: precision {precision!r} is not available with {runtime} (f32; bf16: openvino)")
    threads = threads or default_threads()
    if runtime == "openvino":
        return OpenVinoNetwork(path, threads, precision)
    return OnnxRuntimeNetwork(path, ["CPUExecutionProvider"], ort_session_options(threads))
