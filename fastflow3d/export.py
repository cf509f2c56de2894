"""Export a trained FastFlow3D to ONNX and TorchScript, with a metadata file, and check parity against eager.

The exported network is the single-sample FastFlow3D (:class:`SingleSampleNet`):

* inputs ``pc0_compensated`` (N0, 3) float32, pc0 moved into the ego frame of t + dt by ``ego1_from_ego0``
  (``fastflow3d.model.compensate``), and ``pc1`` (N1, 3) float32 as scanned; N0 and N1 are dynamic;
* outputs ``residual`` (N0, 3) float32, the ego-compensated (residual) flow of every pc0 point inside the grid
  (0 outside), and ``valid`` (N0,) bool, True for points inside the grid.

The full flow in the project convention is ``residual + ego_flow(pc0, ego1_from_ego0)``
(``fastflow3d.predictor.Predictor`` does this). An export directory holds ``fastflow3d.onnx`` and/or
``fastflow3d.pt`` and ``metadata.json`` (grid, model settings, preprocessing (ground removal and the teacher's
ground and ego-motion settings), conventions, versions, hashes of the source checkpoint and of each exported file,
the parity measured at export). ONNX uses the dynamo exporter: the legacy exporter mis-exports scatter ops without a
warning, so every export is run once against eager before it is kept.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import sys
import warnings
from pathlib import Path

import numpy as np
import torch
from torch import nn

import icpflow
from fastflow3d.model import FastFlow3D

FORMATS = ("onnx", "torchscript")
FILE_NAMES = {"onnx": "fastflow3d.onnx", "torchscript": "fastflow3d.pt"}
METADATA_NAME = "metadata.json"
METADATA_VERSION = 1
INPUT_NAMES = ("pc0_compensated", "pc1")
OUTPUT_NAMES = ("residual", "valid")
PARITY_TOLERANCE = 1e-4  # metres, max abs difference between an export and eager
FLOW_CONVENTION = (
    "Inputs: pc0_compensated (N0, 3) float32 = the scan at t moved into the ego frame of t + dt by ego1_from_ego0 "
    "(4x4 rigid, maps the ego frame of t to the ego frame of t + dt); pc1 (N1, 3) float32 = the scan at t + dt in "
    "its own ego frame; metres. Outputs: residual (N0, 3) float32 = ego-compensated flow of each pc0 point "
    "(0 where valid is False); valid (N0,) bool = the point lies inside the grid. Full flow (pc0 + flow is the "
    "point's position at t + dt in the ego frame of t + dt, the Argoverse 2 convention) = residual + "
    "(ego1_from_ego0 * pc0 - pc0); points outside the grid move with the ego motion only."
)


class ExportError(ValueError):
    """An export that cannot be made or that disagrees with eager. The message is one line."""


class SingleSampleNet(nn.Module):
    """FastFlow3D on one pair: ``forward(pc0_compensated (N0, 3), pc1 (N1, 3)) -> (residual (N0, 3), valid (N0,))``.

    The batch indices are built inside (all zeros), so the exported graph takes the two point clouds only.
    """

    def __init__(self, model: FastFlow3D):
        super().__init__()
        self.model = model

    def forward(self, pc0_compensated: torch.Tensor, pc1: torch.Tensor):
        batch0 = torch.zeros_like(pc0_compensated[:, 0], dtype=torch.int64)
        batch1 = torch.zeros_like(pc1[:, 0], dtype=torch.int64)
        return self.model(pc0_compensated, batch0, pc1, batch1, 1)


def sha256_file(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def grid_metadata(model: FastFlow3D) -> dict:
    """The pillar grid of ``model``: ranges and cell (metres) and the cell counts."""
    grid = model.grid
    return {"x_range": list(grid.x_range), "y_range": list(grid.y_range), "z_range": list(grid.z_range),
            "cell": grid.cell, "nx": grid.nx, "ny": grid.ny}


def preprocessing_metadata(cfg: dict) -> dict:
    """What runs before the network, from a training config: ``remove_ground`` (the network was trained on, and
    takes, non-ground points only) and ``teacher`` (ICPFlowConfig fields for the ground masks and the ego motion of
    raw scans, ``fastflow3d.data.TEACHER_FIELDS``; None = ``ICPFlowConfig()``'s). A config without ``data`` (a
    checkpoint from before ground removal) means all points and default settings."""
    data = cfg.get("data") or {}
    return {"remove_ground": bool(data.get("remove_ground", False)), "teacher": data.get("teacher"),
            "note": "with remove_ground, the inputs are the non-ground points of each scan (ground masks by "
                    "icpflow.teacher.ground.GroundSegmenter with these teacher fields, or given); ground pc0 points "
                    "get the ego flow"}


def network_metadata(model: FastFlow3D, model_config: dict | None = None, checkpoint=None,
                     preprocessing: dict | None = None) -> dict:
    """Metadata shared by exports and checkpoints: grid, model settings, preprocessing (see
    :func:`preprocessing_metadata`), conventions, versions, source hash."""
    source = None
    if checkpoint is not None:
        source = {"path": str(Path(checkpoint).resolve()), "sha256": sha256_file(checkpoint)}
    return {
        "metadata_version": METADATA_VERSION,
        "network": "FastFlow3D (single sample)",
        "grid": grid_metadata(model),
        "model": model_config,
        "preprocessing": preprocessing or preprocessing_metadata({}),
        "inputs": [{"name": INPUT_NAMES[0], "shape": ["N0", 3], "dtype": "float32"},
                   {"name": INPUT_NAMES[1], "shape": ["N1", 3], "dtype": "float32"}],
        "outputs": [{"name": OUTPUT_NAMES[0], "shape": ["N0", 3], "dtype": "float32"},
                    {"name": OUTPUT_NAMES[1], "shape": ["N0"], "dtype": "bool"}],
        "flow_convention": FLOW_CONVENTION,
        "package_version": icpflow.__version__,
        "torch_version": torch.__version__,
        "source_checkpoint": source,
    }


def check_inputs(model: FastFlow3D, n0: int, n1: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Two uniform random clouds over the grid and a 10 % margin around it (so some points fall outside)."""
    gen = torch.Generator().manual_seed(seed)
    grid = model.grid
    low = torch.tensor([grid.x_range[0], grid.y_range[0], grid.z_range[0]], dtype=torch.float32)
    high = torch.tensor([grid.x_range[1], grid.y_range[1], grid.z_range[1]], dtype=torch.float32)
    low, high = low - 0.1 * (high - low), high + 0.1 * (high - low)
    return tuple(torch.rand(n, 3, generator=gen) * (high - low) + low for n in (n0, n1))


#: (N0, N1, seed) of the clouds every export is checked on; the first one is also the tracing example
CHECK_SIZES = ((3000, 2500, 0), (257, 4100, 1), (6000, 40, 2))


@contextlib.contextmanager
def quiet_exporters():
    """Silence the exporters' progress logs and deprecation warnings for the duration (levels are restored)."""
    loggers = [logging.getLogger(name) for name in ("torch.onnx", "onnxscript", "onnx_ir")]
    levels = [logger.level for logger in loggers]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", (DeprecationWarning, FutureWarning))
        for logger in loggers:
            logger.setLevel(logging.ERROR)
        try:
            yield
        finally:
            for logger, level in zip(loggers, levels):
                logger.setLevel(level)


def _atomic_target(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def export_onnx(net: SingleSampleNet, path: Path) -> None:
    """Write ``net`` as ONNX (dynamo exporter, dynamic N0 and N1) to ``path`` atomically."""
    try:
        import onnxscript  # noqa: F401  (the dynamo exporter needs it)
    except ImportError:
        raise ExportError("ONNX export needs onnx, onnxscript and onnxruntime: pip install 'icpflow[export]'") from None
    example = check_inputs(net.model, *CHECK_SIZES[0])
    n0, n1 = torch.export.Dim("n0", min=1), torch.export.Dim("n1", min=1)
    tmp = _atomic_target(path)
    try:
        torch.onnx.export(net, example, str(tmp), dynamo=True, external_data=False, verbose=False,
                          input_names=list(INPUT_NAMES), output_names=list(OUTPUT_NAMES),
                          dynamic_shapes={INPUT_NAMES[0]: {0: n0}, INPUT_NAMES[1]: {0: n1}})
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def export_torchscript(net: SingleSampleNet, path: Path) -> None:
    """Write ``net`` traced to TorchScript (CPU; point counts stay dynamic) to ``path`` atomically."""
    example = check_inputs(net.model, *CHECK_SIZES[0])
    with torch.no_grad():
        traced = torch.jit.trace(net, example, check_trace=False)
    tmp = _atomic_target(path)
    try:
        torch.jit.save(traced, str(tmp))
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def measure_parity(net: SingleSampleNet, runner) -> float:
    """Max abs difference (m) of ``runner``'s residual (numpy in, numpy out) against eager on
    :data:`CHECK_SIZES`; the validity masks must match."""
    worst = 0.0
    for n0, n1, seed in CHECK_SIZES:
        pc0, pc1 = check_inputs(net.model, n0, n1, seed + 100)
        with torch.no_grad():
            expected, valid = net(pc0, pc1)
        residual, got_valid = runner(pc0.numpy(), pc1.numpy())
        if np.shape(residual) != tuple(expected.shape) or not np.array_equal(got_valid, valid.numpy()):
            raise ExportError(f"export disagrees with eager on N0={n0}, N1={n1}: shape or validity mask differs")
        worst = max(worst, float(np.abs(residual - expected.numpy()).max(initial=0.0)))
    return worst


def export_model(model: FastFlow3D, out_dir: str | os.PathLike, formats=FORMATS, *, model_config: dict | None = None,
                 checkpoint=None, preprocessing: dict | None = None, tolerance: float = PARITY_TOLERANCE) -> dict:
    """Export ``model`` (eval mode is set) in ``formats`` to ``out_dir``; returns the metadata written.

    Each export is loaded back and compared with eager on random clouds of several sizes; an export off by more
    than ``tolerance`` metres raises :class:`ExportError` and is not kept. ``metadata.json`` is written last.
    """
    formats = tuple(formats)
    unknown = [name for name in formats if name not in FORMATS]
    if unknown or not formats:
        raise ExportError(f"unknown export format(s) {unknown or formats}; use {', '.join(FORMATS)} or all")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / METADATA_NAME).unlink(missing_ok=True)  # a directory without metadata is not a (complete) export
    net = SingleSampleNet(model.eval()).eval()
    metadata = network_metadata(model, model_config, checkpoint, preprocessing)
    metadata["files"], metadata["parity_max_abs_m"] = {}, {}
    from fastflow3d.predictor import OnnxRuntimeNetwork, load_network  # imports this module

    writers = {"onnx": export_onnx, "torchscript": export_torchscript}
    for name in formats:
        path = out_dir / FILE_NAMES[name]
        with quiet_exporters():
            writers[name](net, path)
            runner = (OnnxRuntimeNetwork(path, ["CPUExecutionProvider"]) if name == "onnx"
                      else load_network(path, name, "cpu"))
            error = measure_parity(net, runner)
        if not error <= tolerance:
            path.unlink()
            raise ExportError(f"{path}: {name} export differs from eager by {error:.3g} m (> {tolerance:g} m); "
                              "not kept")
        metadata["files"][name] = {"path": path.name, "sha256": sha256_file(path)}
        metadata["parity_max_abs_m"][name] = error
    if "onnx" in formats:
        import onnx

        opsets = onnx.load(str(out_dir / FILE_NAMES["onnx"]), load_external_data=False).opset_import
        metadata["onnx_opset"] = next(entry.version for entry in opsets if entry.domain in ("", "ai.onnx"))
    write_json(out_dir / METADATA_NAME, metadata)
    return metadata


def write_json(path: Path, content: dict) -> None:
    """Write ``content`` as indented JSON to ``path`` atomically."""
    tmp = _atomic_target(path)
    tmp.write_text(json.dumps(content, indent=2) + "\n")
    os.replace(tmp, path)


def export_checkpoint(checkpoint: str | os.PathLike, out_dir: str | os.PathLike | None = None,
                      formats=FORMATS) -> Path:
    """Export a training checkpoint (``fastflow3d.checkpoint.load_student``); ``out_dir`` defaults to
    ``<checkpoint's directory>/export``. Returns the export directory."""
    from fastflow3d.checkpoint import load_student

    checkpoint = Path(checkpoint)
    if not checkpoint.is_file():
        raise ExportError(f"{checkpoint}: checkpoint not found")
    model, cfg = load_student(checkpoint, map_location="cpu")
    out_dir = checkpoint.parent / "export" if out_dir is None else Path(out_dir)
    export_model(model, out_dir, formats, model_config=dict(cfg.get("model") or {}), checkpoint=checkpoint,
                 preprocessing=preprocessing_metadata(cfg))
    return out_dir


def parse_formats(value: str) -> tuple[str, ...]:
    """``onnx``, ``torchscript``, ``all`` or a comma-separated list -> format names."""
    names = [part.strip() for part in str(value).split(",") if part.strip()]
    return FORMATS if names == ["all"] else tuple(names)


def run_export(cfg) -> int:
    """``export.py``: export ``cfg.checkpoint`` in ``cfg.format`` to ``cfg.out_dir``; print what was written.

    Returns the exit status: 0 exported, 2 could not export (one line on stderr).
    """
    from omegaconf import OmegaConf

    if OmegaConf.is_missing(cfg, "checkpoint") or not cfg.checkpoint:
        print("export: pass checkpoint=<path to a training .ckpt>", file=sys.stderr)
        return 2
    try:
        out_dir = export_checkpoint(cfg.checkpoint, cfg.out_dir, parse_formats(cfg.format))
    except (ValueError, RuntimeError, OSError) as error:
        print(f"export: {' '.join(str(error).split())}", file=sys.stderr)
        return 2
    metadata = json.loads((out_dir / METADATA_NAME).read_text())
    for name, entry in metadata["files"].items():
        print(f"export: {name} -> {out_dir / entry['path']} (max |export - eager| "
              f"{metadata['parity_max_abs_m'][name]:.2e} m)")
    print(f"export: metadata -> {out_dir / METADATA_NAME}")
    return 0
