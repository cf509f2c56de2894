"""Student checkpoints: the network from its config, and a trained network back from a Lightning checkpoint.

Contract (``fastflow3d.training.student_module.StudentModule`` writes it; export and evaluation read it): the
checkpoint's ``hyper_parameters`` is ``{"cfg": <the full resolved training config as plain dict>}``; ``cfg["model"]`` is
``{"_target_": "fastflow3d.network.model.FastFlow3D", <FastFlow3D keyword arguments>}``; the network's weights are the
``state_dict`` entries ``model.<name>``. Checkpoints are read with ``torch.load(..., weights_only=True)``, and the
``_target_``s of their stored config are read as today's paths (:data:`MOVED_TARGETS`).
"""

from __future__ import annotations

from pathlib import Path

import torch

from fastflow3d.network.model import FastFlow3D
from icpflow.core.deprecation import MOVED_TARGETS as ICPFLOW_TARGETS
from icpflow.core.deprecation import current_target
from icpflow.core.stops import raise_stop_behind

MODEL_TARGET = "fastflow3d.network.model.FastFlow3D"

#: The modules whose objects a stored training config names as ``_target_`` (``model``, ``module``, ``scheduler``,
#: ``callbacks``) and that have moved since a release wrote it: old module -> module today (since the packages were
#: split into rooms, ``fastflow3d`` in 0.2; ``icpflow``'s from ``icpflow.core.deprecation``). A checkpoint keeps the
#: paths of the code that wrote it; :func:`read_checkpoint` is the one place a stored config is read, and reads them
#: as today's (``tests/fixtures/release_0_1``). Export metadata names no module that is instantiated (its ``model``
#: entry is a copy of the checkpoint's, for the reader).
MOVED_TARGETS = {
    "fastflow3d.model": "fastflow3d.network.model",
    "fastflow3d.module": "fastflow3d.training.student_module",
    "fastflow3d.schedules": "fastflow3d.training.schedules",
    "fastflow3d.callbacks": "fastflow3d.training.callbacks",
    **ICPFLOW_TARGETS,
}


class CheckpointError(ValueError):
    """A file is not a readable student checkpoint. The message is one line naming the file."""


def build_student(model_cfg: dict) -> FastFlow3D:
    """A fresh FastFlow3D from ``cfg["model"]`` (``_target_`` must be ``MODEL_TARGET``; lists become tuples)."""
    kwargs = dict(model_cfg)
    target = kwargs.pop("_target_", None)
    if target != MODEL_TARGET:
        raise ValueError(f"model config: _target_ must be {MODEL_TARGET}, got {target!r}")
    return FastFlow3D(**{k: tuple(v) if isinstance(v, list) else v for k, v in kwargs.items()})


def _first_line(error: Exception) -> str:
    """The cause in one line; torch's advice to load unsafe files (``weights_only=False``) is never repeated."""
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    if lines and lines[0].startswith("Weights only load failed"):
        detail = next((line for line in lines if line.startswith("WeightsUnpickler error")), "")
        detail = detail.split(". Please", 1)[0].split(" was not an allowed global", 1)[0]
        return "it holds objects other than tensors and plain data" + (f": {detail}" if detail else "")
    return lines[0] if lines else type(error).__name__


def current_targets(node):
    """A stored config (dicts, lists, plain values) with each ``_target_`` of a moved module (:data:`MOVED_TARGETS`)
    named by today's path; everything else as it is."""
    if isinstance(node, dict):
        return {
            key: _current_target(value) if key == "_target_" else current_targets(value) for key, value in node.items()
        }
    if isinstance(node, list):
        return [current_targets(value) for value in node]
    return node


def _current_target(target):
    return current_target(target, MOVED_TARGETS)


def read_checkpoint(path, map_location="cpu") -> dict:
    """The contents of a torch checkpoint file (tensors and plain data only), its stored config's ``_target_``s read
    as today's paths (:func:`current_targets`); a missing, truncated or foreign file raises :class:`CheckpointError`."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint does not exist")
    try:
        checkpoint = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as error:  # torch raises many types for a file that is not a (safe) checkpoint
        raise_stop_behind(error)
        raise CheckpointError(
            f"{path}: not a readable torch checkpoint, truncated or damaged? ({_first_line(error)})"
        ) from None
    if not isinstance(checkpoint, dict):
        raise CheckpointError(f"{path}: not a checkpoint (holds a {type(checkpoint).__name__}, not a dict)")
    hparams = checkpoint.get("hyper_parameters")
    if isinstance(hparams, dict) and "cfg" in hparams:
        checkpoint["hyper_parameters"] = {**hparams, "cfg": current_targets(hparams["cfg"])}
    return checkpoint


def load_student(path, map_location="cpu") -> tuple[FastFlow3D, dict]:
    """``(FastFlow3D in eval mode, training config dict)`` from a student checkpoint written by ``train.py``."""
    path = Path(path)
    checkpoint = read_checkpoint(path, map_location)
    hparams = checkpoint.get("hyper_parameters")
    cfg = hparams.get("cfg") if isinstance(hparams, dict) else None
    if not isinstance(cfg, dict) or not isinstance(cfg.get("model"), dict) or "state_dict" not in checkpoint:
        raise CheckpointError(
            f"{path}: not a FastFlow3D student checkpoint (no hyper_parameters.cfg.model or no state_dict)"
        )
    try:
        model = build_student(cfg["model"])
        state = {k[len("model.") :]: v for k, v in checkpoint["state_dict"].items() if k.startswith("model.")}
        model.load_state_dict(state)
    except (ValueError, TypeError, RuntimeError) as error:
        raise CheckpointError(f"{path}: weights do not fit its model config ({_first_line(error)})") from None
    return model.to(map_location).eval(), cfg
