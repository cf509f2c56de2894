"""What opening a model file may run, checked before it is opened: a ``.pt2`` archive is refused where
``torch.export.load`` would unpickle or execute any part of it (:func:`check_pt2`); a legacy TorchScript ``.pt``
runs code when loaded and is only opened when asked for by name (:data:`TORCHSCRIPT_WARNING`, said each time).
Checkpoints are read with ``torch.load(weights_only=True)`` (``fastflow3d.artifact.checkpoint``); ``.onnx`` files hold
no code."""

from __future__ import annotations

import io
import json
import re
import zipfile
from pathlib import Path

import torch

from fastflow3d.artifact.file_format import ArtifactError
from icpflow.core.stops import raise_stop_behind

TORCHSCRIPT_WARNING = (
    "a TorchScript file runs code when it is loaded: load it only from a source you trust "
    "(backend='torchscript', fastflow3d-infer --backend torchscript)"
)


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
                except Exception as error:  # torch's own fallback would unpickle it in full
                    raise_stop_behind(error)
                    raise ArtifactError(f"{path}: refused: {name} is not plain tensors (it could run code)") from None
