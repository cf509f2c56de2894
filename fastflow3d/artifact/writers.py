"""The writers of the exported formats (``fastflow3d.artifact.file_format``): the network (:class:`SingleSampleNet`)
traced on an example pair with dynamic point counts, written atomically (``icpflow.core.atomic``)."""

from __future__ import annotations

import io
from pathlib import Path

import torch

from fastflow3d.artifact.file_format import INPUT_NAMES, OUTPUT_NAMES, SingleSampleNet
from icpflow.core.atomic import atomic_path


def _dynamic_shapes() -> dict:
    n0, n1 = torch.export.Dim("n0", min=1), torch.export.Dim("n1", min=1)
    return {INPUT_NAMES[0]: {0: n0}, INPUT_NAMES[1]: {0: n1}}


def write_onnx(net: SingleSampleNet, path: Path, example: tuple[torch.Tensor, torch.Tensor]) -> None:
    """Write ``net`` as ONNX (dynamo exporter, dynamic N0 and N1, traced on ``example``) to ``path`` atomically.

    The model is serialised in memory and written by Python, so a write error (a full disk) is an OSError, not an
    abort in native code. Raises ImportError when onnxscript (which the dynamo exporter needs) is missing."""
    import onnxscript  # noqa: F401

    program = torch.onnx.export(
        net,
        example,
        dynamo=True,
        verbose=False,
        input_names=list(INPUT_NAMES),
        output_names=list(OUTPUT_NAMES),
        dynamic_shapes=_dynamic_shapes(),
    )
    with atomic_path(path) as tmp:
        tmp.write_bytes(program.model_proto.SerializeToString())


def write_pt2(net: SingleSampleNet, path: Path, example: tuple[torch.Tensor, torch.Tensor]) -> None:
    """Write ``net`` as a ``torch.export`` ExportedProgram (CPU, dynamic N0 and N1, traced on ``example``) to
    ``path`` atomically (serialised in memory first: torch's file writer aborts the process on a full disk)."""
    program = torch.export.export(net, example, dynamic_shapes=_dynamic_shapes())
    buffer = io.BytesIO()
    torch.export.save(program, buffer)
    with atomic_path(path) as tmp:
        tmp.write_bytes(buffer.getbuffer())


WRITERS = {"onnx": write_onnx, "pt2": write_pt2}


def onnx_opset(path: Path) -> int:
    """The default-domain opset of an ONNX file."""
    import onnx

    opsets = onnx.load(str(path), load_external_data=False).opset_import
    return next(entry.version for entry in opsets if entry.domain in ("", "ai.onnx"))
