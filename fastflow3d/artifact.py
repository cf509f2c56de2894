"""The exported FastFlow3D artifact: its network, file names, metadata schema, and how it is written and read.

An export directory holds ``metadata.json`` and one file per format:

* ``fastflow3d.onnx``: ONNX (dynamo exporter), run in ONNX Runtime;
* ``fastflow3d.pt2``: a ``torch.export`` ExportedProgram, run in PyTorch (``torch.export.load``);
* ``fastflow3d.pt``: TorchScript, written by older versions of this code. It is only read (``torch.jit`` is
  deprecated): keep it while such exports are in use, re-export their checkpoints to replace them.

The network of every format is :class:`SingleSampleNet`:

* inputs ``pc0_compensated`` (N0, 3) float32, pc0 moved into the ego frame of t + dt by ``ego1_from_ego0``
  (``fastflow3d.model.compensate``), and ``pc1`` (N1, 3) float32 as scanned; N0 and N1 are dynamic;
* outputs ``residual`` (N0, 3) float32, the ego-compensated (residual) flow of every pc0 point inside the grid
  (0 outside), and ``valid`` (N0,) bool, True for points inside the grid.

``metadata.json`` (:func:`network_metadata`) holds the grid, model settings, the input contract (``input``:
``fastflow3d.contract``, the height frame, ground removal and its settings, the ego-motion settings), conventions,
versions, the source checkpoint's hash, and (``files``) the name and hash of each exported file with the parity
measured at export. ``fastflow3d.export`` writes artifacts,
``fastflow3d.predictor`` runs them.
"""

from __future__ import annotations

import hashlib
import importlib.util
import io
import json
import os
import re
import zipfile
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.export.passes import move_to_device_pass

import icpflow
from fastflow3d.contract import InputContract
from fastflow3d.model import FastFlow3D
from icpflow.atomic import atomic_path, write_text_atomic
from icpflow.entry import one_line

FORMATS = ("onnx", "pt2")  # what an export writes
LEGACY_FORMATS = ("torchscript",)  # read only: exports of older versions
FILE_NAMES = {"onnx": "fastflow3d.onnx", "pt2": "fastflow3d.pt2"}
LEGACY_FILE_NAMES = ("fastflow3d.pt",)
SUFFIX_FORMATS = {".onnx": "onnx", ".pt2": "pt2", ".pt": "torchscript"}
METADATA_NAME = "metadata.json"
METADATA_VERSION = 2  # 2: the input contract as ``input``; 1: ``preprocessing`` (read by fastflow3d.contract.upgrade)
INPUT_NOTE = (
    "inputs are in the height frame (ground near frame.ground_z; a scan in another frame is lifted first); with "
    "remove_ground, the network gets the non-ground points of each scan (ground masks by "
    "icpflow.ground.GroundSegmenter with these settings, or given) inside the grid; ground pc0 points get "
    "the ego flow (fastflow3d.contract)"
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
    form of ``fastflow3d.contract.InputContract``; default: every point, the synthetic frame, the model's grid),
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
        metadata = json.loads(path.read_text())
    except FileNotFoundError:
        raise ArtifactError(f"{path.parent}: no {METADATA_NAME} (not an export directory; see export.py)") from None
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
    if not file.is_file():
        raise ArtifactError(f"{file}: file listed in {METADATA_NAME} is missing")
    if sha256_file(file) != entry.get("sha256"):
        raise ArtifactError(f"{file}: file changed after export (sha256 differs from {METADATA_NAME})")
    return file


# ---------------------------------------------------------------------------------------------------- writing


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


# ---------------------------------------------------------------------------------------------------- reading


class OnnxRuntimeNetwork:
    """An exported ``.onnx`` in ONNX Runtime: ``(pc0_compensated, pc1) -> (residual, valid)`` numpy arrays."""

    def __init__(self, path: Path, providers=None, options=None):
        """``options``: an ``onnxruntime.SessionOptions`` (``fastflow3d.runtime.ort_session_options``), or None for
        ONNX Runtime's defaults."""
        try:
            import onnxruntime
        except ImportError:
            raise ArtifactError(f"{path}: running .onnx needs onnxruntime (pip install 'icpflow[export]')") from None
        available = onnxruntime.get_available_providers()
        if providers is None:
            providers = [name for name in ("CUDAExecutionProvider", "CPUExecutionProvider") if name in available]
        try:
            self.session = onnxruntime.InferenceSession(str(path), options, providers=list(providers))
        except Exception as error:  # onnxruntime raises its own exception types for damaged or foreign files
            raise ArtifactError(f"{path}: cannot load ONNX model: {one_line(error)}") from None
        names = tuple(entry.name for entry in self.session.get_inputs())
        if names != INPUT_NAMES:
            raise ArtifactError(f"{path}: ONNX inputs are {names}, expected {INPUT_NAMES} (not a FastFlow3D export)")

    def __call__(self, pc0_compensated: np.ndarray, pc1: np.ndarray):
        residual, valid = self.session.run(list(OUTPUT_NAMES), {INPUT_NAMES[0]: pc0_compensated, INPUT_NAMES[1]: pc1})
        return residual, valid


class TorchNetwork:
    """A :class:`SingleSampleNet`, a loaded ExportedProgram's module or a TorchScript trace on ``device``: numpy in,
    numpy out (float32 residual). ``bf16``: the module runs under bfloat16 autocast (the points stay float32)."""

    def __init__(self, module, device: str = "cpu", bf16: bool = False):
        self.module, self.device, self.bf16 = module, torch.device(device), bool(bf16)

    def __call__(self, pc0_compensated: np.ndarray, pc1: np.ndarray):
        with torch.inference_mode(), torch.autocast(self.device.type, torch.bfloat16, enabled=self.bf16):
            residual, valid = self.module(
                torch.from_numpy(pc0_compensated).to(self.device), torch.from_numpy(pc1).to(self.device)
            )
        return residual.float().cpu().numpy(), valid.cpu().numpy()


TORCHSCRIPT_WARNING = (
    "a TorchScript file runs code when it is loaded: load it only from a source you trust "
    "(backend='torchscript', fastflow3d-infer --backend torchscript)"
)


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


# What a ``torch.export.save`` archive of a FastFlow3D network holds (``<archive>/...``): version and layout
# markers, the programs as JSON, the weights as raw tensors with their JSON config, the constants' JSON config and
# the sample inputs. Anything else (compiled AOTInductor libraries, custom or pickled objects) is refused.
_PT2_MEMBERS = re.compile(
    r"[^/]+/(byteorder|archive_format|archive_version|\.data/version|\.data/serialization_id|models/[\w.-]+\.json"
    r"|data/weights/(weight_\d+|[\w.-]+_weights_config\.json)|data/constants/[\w.-]+_constants_config\.json"
    r"|data/sample_inputs/[\w.-]+\.pt)"
)


def check_pt2(path: Path) -> None:
    """Refuse (one-line ``ArtifactError``) a ``.pt2`` archive that ``torch.export.load`` would unpickle or execute.

    ``torch.export.load`` reads a weight or constant marked ``use_pickle`` with ``torch.load(weights_only=False)``,
    custom objects with the pickler, sample inputs with a fallback to ``weights_only=False``, and AOTInductor
    libraries as shared objects; the sha256 in ``metadata.json`` proves nothing, since whoever crafted the archive
    wrote it too. So: every member must be one an exported program holds (``_PT2_MEMBERS``), no weight or constant
    may be pickled (constants: none at all but plain tensors), and the sample inputs must load with
    ``weights_only=True``."""
    try:
        archive = zipfile.ZipFile(path)
    except (OSError, zipfile.BadZipFile) as error:
        raise ArtifactError(f"{path}: cannot load pt2: not a torch.export archive ({error})") from None
    with archive:
        for name in archive.namelist():
            if not _PT2_MEMBERS.fullmatch(name):
                raise ArtifactError(f"{path}: refused: member {name!r} is not part of an exported program")
            if name.endswith("_config.json"):
                try:
                    entries = json.loads(archive.read(name)).get("config", {})
                except (ValueError, AttributeError):
                    raise ArtifactError(f"{path}: refused: {name} is not a torch.export config") from None
                if not isinstance(entries, dict):
                    raise ArtifactError(f"{path}: refused: {name} is not a torch.export config")
                for key, entry in entries.items():
                    plain = isinstance(entry, dict) and entry.get("use_pickle") is False and "tensor_meta" in entry
                    if not plain:
                        raise ArtifactError(f"{path}: refused: {key!r} in {name} is stored pickled (it could run code)")
            elif "/data/sample_inputs/" in name:
                try:
                    torch.load(io.BytesIO(archive.read(name)), map_location="cpu", weights_only=True)
                except Exception:  # torch's own fallback would unpickle it in full
                    raise ArtifactError(f"{path}: refused: {name} is not plain tensors (it could run code)") from None


def load_network(path: Path, kind: str, device: str = "cpu"):
    """The runnable network (numpy in, numpy out) of one exported file of format ``kind``: the one place model
    files are loaded. ``.pt2`` archives pass :func:`check_pt2` first; ``torchscript`` (legacy ``.pt``) can run
    code when loaded and is only read when the caller asked for it by name (see ``choose_format``)."""
    if kind == "onnx":
        return OnnxRuntimeNetwork(path)
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
        raise ArtifactError(f"{path}: cannot load {kind}: {one_line(error)[:300]}") from None
    return TorchNetwork(module, device)
