"""``fastflow3d-train`` (``train.py``) and ``fastflow3d-export`` (``export.py``): the entry points whose configs this
room types (``fastflow3d.training.options``: ``conf/train.yaml``, ``conf/export.yaml``). Export's own work is
``fastflow3d.artifact.export.run_export``."""

from __future__ import annotations

import sys

from omegaconf import DictConfig

from fastflow3d.artifact.export import run_export
from fastflow3d.training.options import register
from fastflow3d.training.run_folder import TrainError
from fastflow3d.training.trainer import fit
from icpflow.core.console import quiet
from icpflow.core.entry_points import hydra_entry
from icpflow.core.errors_and_signals import reported


def training_task(cfg: DictConfig) -> None:
    """The Hydra task of :func:`train_main`: ``fit``, a TrainError's message as the one line."""
    quiet()
    with reported("train", TrainError):
        fit(cfg)


def export_task(cfg: DictConfig) -> None:
    """The Hydra task of :func:`export_main`: ``run_export``, exiting with its status."""
    quiet()
    with reported("export"):
        status = run_export(cfg)
        if status:
            sys.exit(status)


def train_main() -> None:
    """``fastflow3d-train`` and ``train.py``: train the student as ``conf/train.yaml`` and the command line say."""
    register()  # train_schema in Hydra's ConfigStore: the structured config conf/train.yaml extends
    hydra_entry("train", "train", training_task)


def export_main() -> None:
    """``fastflow3d-export`` and ``export.py``: export a checkpoint as ``conf/export.yaml`` and the command line say."""
    register()  # export_schema in Hydra's ConfigStore: the structured config conf/export.yaml extends
    hydra_entry("export", "export", export_task)
