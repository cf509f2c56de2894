"""The model that ships inside the package: ``experiment=synthetic_cpu``'s student, so that ``fastflow3d-infer SCANS``
and ``Predictor.load()`` run without a model of one's own.

It is an export directory (``fastflow3d.artifact.file_format``: ``metadata.json``, the float32 and int8 ONNX networks;
no ``.pt2``: ONNX Runtime is a dependency, torch's exported program is not needed to run it) with ``MODEL_CARD.md``
(how it was trained, what it scores, what it is not). Its metadata carries a ``shipped`` entry (name, card, the
command that rebuilt it); ``benchmarks/ship_model.py`` rebuilds the folder from a fresh labelling and training run.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from fastflow3d.artifact.file_format import METADATA_NAME, ArtifactError

#: the shipped model's folder name under ``fastflow3d/artifact/models/``
SHIPPED_NAME = "synthetic_cpu"
#: its card, beside its files
CARD_NAME = "MODEL_CARD.md"


def shipped_model() -> Path:
    """The shipped model's export directory (one-line error where an install lost it)."""
    path = Path(str(resources.files("fastflow3d.artifact") / "models" / SHIPPED_NAME))
    if not (path / METADATA_NAME).is_file():
        raise ArtifactError(
            f"{path}: the shipped model is missing from this install (reinstall icpflow, or name a model of your own)"
        )
    return path


def shipped_label(metadata: dict) -> str | None:
    """How a run names the shipped model (None for any other model): its name, the release and where its card is."""
    shipped = metadata.get("shipped")
    if not isinstance(shipped, dict):
        return None
    version = metadata.get("package_version", "?")
    return (
        f"the shipped {shipped.get('name', SHIPPED_NAME)} student (icpflow {version}; trained on the synthetic "
        f"world only: {shipped_model() / CARD_NAME})"
    )
