"""The exported FastFlow3D artifact's file format: its network, file names, metadata schema, and how the metadata and
the files it lists are read.

An export directory holds ``metadata.json`` and one file per format:

* ``fastflow3d.onnx``: ONNX (dynamo exporter), run in ONNX Runtime;
* ``fastflow3d.pt2``: a ``torch.export`` ExportedProgram, run in PyTorch (``torch.export.load``);
* ``fastflow3d.int8.onnx`` (``export.py ... int8=true``, listed as ``onnx_int8``): the ONNX network with int8
  convolutions (``fastflow3d.artifact.quantize``), run in ONNX Runtime with ``precision="int8"`` (or ``"auto"``);
* ``fastflow3d.pt``: TorchScript, written by older versions of this code. It is only read (``torch.jit`` is
  deprecated): keep it while such exports are in use, re-export their checkpoints to replace them.

The network of every format is :class:`SingleSampleNet`:

* inputs ``pc0_compensated`` (N0, 3) float32, pc0 moved into the ego frame of t + dt by ``ego1_from_ego0``
  (``fastflow3d.network.model.compensate``), and ``pc1`` (N1, 3) float32 as scanned; N0 and N1 are dynamic;
* outputs ``residual`` (N0, 3) float32, the ego-compensated (residual) flow of every pc0 point inside the grid
  (0 outside), and ``valid`` (N0,) bool, True for points inside the grid.

``metadata.json`` (:func:`network_metadata`) holds the grid, model settings, the input contract (``input``:
``fastflow3d.network.contract``, the height frame, ground removal and its settings, the ego-motion settings),
conventions, versions, the source checkpoint's hash, and (``files``) the name and hash of each exported file with the
parity measured at export. ``fastflow3d.artifact.writers`` writes each format, ``fastflow3d.artifact.export`` writes
whole artifacts, ``fastflow3d.artifact.engines`` opens them (``fastflow3d.artifact.safe_loading`` checks a ``.pt2``
first), ``fastflow3d.inference.predictor`` runs them.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import torch
from torch import nn

import icpflow
from fastflow3d.network.contract import InputContract
from fastflow3d.network.model import FastFlow3D
from icpflow.core.atomic import write_text_atomic
from icpflow.core.errors_and_signals import one_line
from icpflow.core.files import NotAFile, not_a_file, read_text

FORMATS = ("onnx", "pt2")  # what an export writes
LEGACY_FORMATS = ("torchscript",)  # read only: exports of older versions
FILE_NAMES = {"onnx": "fastflow3d.onnx", "pt2": "fastflow3d.pt2"}
INT8 = "onnx_int8"  # the int8 network's entry in ``files`` (written on request, from the onnx one)
INT8_FILE_NAME = "fastflow3d.int8.onnx"
LEGACY_FILE_NAMES = ("fastflow3d.pt",)
SUFFIX_FORMATS = {".onnx": "onnx", ".pt2": "pt2", ".pt": "torchscript"}
METADATA_NAME = "metadata.json"
METADATA_VERSION = (
    2  # 2: the input contract as ``input``; 1: ``preprocessing`` (read by fastflow3d.network.contract.upgrade)
)
INPUT_NOTE = (
    "inputs are in the height frame (ground near frame.ground_z; a scan in another frame is lifted first); with "
    "remove_ground, the network gets the non-ground points of each scan (ground masks by "
    "icpflow.scans.ground.GroundSegmenter with these settings, or given) inside the grid; ground pc0 points get "
    "the ego flow (fastflow3d.network.contract)"
)
INPUT_NAMES = ("pc0_compensated", "pc1")
OUTPUT_NAMES = ("residual", "valid")
FLOW_CONVENTION = (
    "Inputs: pc0_compensated (N0, 3) float32 = the scan at t moved into the ego frame of t + dt by ego1_from_ego0 "
    "(4x4 rigid, maps the ego frame of t to the ego frame of t + dt); pc1 (N1, 3) float32 = the scan at t + dt in "
    "its own ego frame; metres. Outputs: residual (N0, 3) float32 = ego-compensated flow of each pc0 point "
    "(0 where valid is False); valid (N0,) bool = the point lies inside the grid. Full flow (pc0 + flow is the "
    "point's position at t + dt in the ego frame of t + dt, the Argoverse 2 convention) = residual + "
    "(ego1_from_ego0 * pc0 - pc0); points outside the grid move with the ego motion only."
)


class ArtifactError(ValueError):
    """An artifact that cannot be read or run (missing, changed, foreign). The message is one line."""


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


# ---------------------------------------------------------------------------------------------------- metadata


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
    return {
        "x_range": list(grid.x_range),
        "y_range": list(grid.y_range),
        "z_range": list(grid.z_range),
        "cell": grid.cell,
        "nx": grid.nx,
        "ny": grid.ny,
    }


def network_metadata(
    model: FastFlow3D, model_config: dict | None = None, checkpoint=None, contract: InputContract | None = None
) -> dict:
    """Metadata shared by exports and checkpoints: grid, model settings, the input contract (``input``, the stored
    form of ``fastflow3d.network.contract.InputContract``; default: every point, the synthetic frame, the model's grid),
    conventions, versions, source hash."""
    source = None
    if checkpoint is not None:
        source = {"path": str(Path(checkpoint).resolve()), "sha256": sha256_file(checkpoint)}
    return {
        "metadata_version": METADATA_VERSION,
        "network": "FastFlow3D (single sample)",
        "grid": grid_metadata(model),
        "model": model_config,
        "input": (contract or InputContract(remove_ground=False, grid=model.grid)).to_dict(),
        "input_note": INPUT_NOTE,
        "inputs": [
            {"name": INPUT_NAMES[0], "shape": ["N0", 3], "dtype": "float32"},
            {"name": INPUT_NAMES[1], "shape": ["N1", 3], "dtype": "float32"},
        ],
        "outputs": [
            {"name": OUTPUT_NAMES[0], "shape": ["N0", 3], "dtype": "float32"},
            {"name": OUTPUT_NAMES[1], "shape": ["N0"], "dtype": "bool"},
        ],
        "flow_convention": FLOW_CONVENTION,
        "package_version": icpflow.__version__,
        "torch_version": torch.__version__,
        "source_checkpoint": source,
    }


def write_metadata(out_dir: Path, metadata: dict) -> Path:
    """Write ``metadata`` as ``<out_dir>/metadata.json`` (indented JSON, atomically); returns its path."""
    path = Path(out_dir) / METADATA_NAME
    write_text_atomic(path, json.dumps(metadata, indent=2) + "\n")
    return path


def read_metadata(path: Path) -> dict:
    """``metadata.json`` of an export directory (one-line error if missing or not an export's)."""
    try:
        metadata = json.loads(read_text(path))
    except FileNotFoundError:
        raise ArtifactError(f"{path.parent}: no {METADATA_NAME} (not an export directory; see export.py)") from None
    except NotAFile as error:  # a FIFO, a device, a file too large: its own line
        raise ArtifactError(str(error)) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ArtifactError(f"{path}: cannot read export metadata: {one_line(error)}") from None
    if not isinstance(metadata, dict) or not isinstance(metadata.get("files"), dict):
        raise ArtifactError(f"{path}: not FastFlow3D export metadata (no 'files' entry)")
    version = metadata.get("metadata_version", 1)
    if not isinstance(version, int) or isinstance(version, bool) or version > METADATA_VERSION:
        raise ArtifactError(
            f"{path}: metadata_version {version!r} is not one this version reads (<= {METADATA_VERSION}); "
            "a newer icpflow wrote it: upgrade icpflow"
        )
    return metadata


def sibling_metadata(path: Path, kind: str) -> dict:
    """The metadata next to an exported file if it describes exactly this file (same name and hash), else {}."""
    meta_path = path.parent / METADATA_NAME
    if not meta_path.is_file():
        return {}
    try:
        metadata = read_metadata(meta_path)
    except ArtifactError:
        return {}
    entry = metadata["files"].get(kind)
    if not isinstance(entry, dict):
        return {}
    same = entry.get("path") == path.name and entry.get("sha256") == sha256_file(path)
    return metadata if same else {}


def listed_file(export_dir: Path, metadata: dict, kind: str) -> Path:
    """The file of format ``kind`` listed in an export directory's metadata, checked against its recorded hash.
    The entry must name a file directly inside ``export_dir`` (no folder, no ``..``, not absolute): a metadata file
    from elsewhere cannot point the loader at another file."""
    entry = metadata["files"].get(kind)
    if not entry:
        raise ArtifactError(f"{export_dir}: the export has no {kind} file (has {', '.join(metadata['files'])})")
    meta_path = export_dir / METADATA_NAME
    if not isinstance(entry, dict) or not isinstance(entry.get("path"), str):
        raise ArtifactError(f"{meta_path}: files.{kind} must be an object with a 'path' string, got {entry!r:.80}")
    name = entry["path"]
    if Path(name).name != name or name in ("", ".", ".."):
        raise ArtifactError(
            f"{meta_path}: files.{kind} path {name!r} leaves the export folder; only a file name is allowed"
        )
    file = export_dir / name
    if (refused := not_a_file(file)) is not None:
        raise ArtifactError(refused)
    if not file.is_file():
        raise ArtifactError(f"{file}: file listed in {METADATA_NAME} is missing")
    if sha256_file(file) != entry.get("sha256"):
        raise ArtifactError(f"{file}: file changed after export (sha256 differs from {METADATA_NAME})")
    return file
