"""The structured configs of ``train.py`` and ``export.py`` (``conf/train.yaml`` and ``conf/export.yaml`` extend
them): every option typed, with its rule (``icpflow.core.settings``), checked as ``label.py``'s and ``eval.py``'s are.

``trainer`` is typed from ``lightning.Trainer``'s own signature (:func:`icpflow.core.settings.signature_schema`), so a
misspelt Trainer argument or a value of the wrong type is refused while Hydra composes, like ours. ``model``,
``optim``, ``scheduler``, ``logger``, ``callbacks`` and ``module`` are ``_target_`` nodes whose group option chooses
the class: their arguments are checked by that class when it is built (before any training step).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import lightning as L
from omegaconf import MISSING

from fastflow3d.training.loss import WEIGHTINGS
from fastflow3d.training.student_module import LOSSES
from icpflow.core.settings import setting, signature_schema, store

#: ``lightning.Trainer``'s keyword arguments, less those ``fastflow3d.training.trainer.build_trainer`` passes itself
TrainerOptions = signature_schema(
    L.Trainer, "TrainerOptions", exclude=("logger", "callbacks", "plugins", "default_root_dir")
)


@dataclass
class AugmentOptions:
    """``data.augment`` (``fastflow3d.training.augment``): training samples only; null = none."""

    yaw_deg: float = setting(20.0, "non_negative")
    flip: bool = True
    height_shift: float = setting(0.1, "non_negative")
    keep_min: float = setting(0.8, "fraction")


@dataclass
class DataOptions:
    """``data`` (``conf/data/shards.yaml``, ``fastflow3d.training.data.ShardDataModule``)."""

    train: str = MISSING
    val: str = MISSING
    batch_size: int = setting(8, "count")
    workers: int = setting(2, "count_or_zero")
    worker_blas_threads: int = setting(1, "count")
    train_points: int | None = setting(None, "count")
    remove_ground: bool = True
    augment: AugmentOptions | None = field(default_factory=AugmentOptions)


@dataclass
class LossOptions:
    """``loss`` (``fastflow3d.training.loss``)."""

    name: str = setting("distillation", choices=LOSSES)
    weighting: str = setting("buckets", choices=WEIGHTINGS)
    bucket_edges: list[float] = setting([0.4, 1.0])
    background_weight: float = setting(1.0, "non_negative")
    object_weight: float = setting(0.0, "non_negative")


@dataclass
class ExportStepOptions:
    """``export``: the best checkpoint exported at the end of fit."""

    formats: list[str] = setting(["onnx", "pt2"])  # [] = no export
    int8: bool = False  # with onnx: also fastflow3d.int8.onnx, calibrated on data.train (fastflow3d.artifact.quantize)
    dir: str = MISSING


@dataclass
class MetricsOptions:
    """``metrics``: validation's scoring and pictures."""

    crop: float | None = setting(32.0, "positive")
    bev_every: int = setting(5, "count_or_zero")


@dataclass
class TrainOptions:
    """``train.py`` (``conf/train.yaml`` and its groups)."""

    data: DataOptions = MISSING
    model: Any = MISSING  # fastflow3d.network.model.FastFlow3D's arguments (conf/model)
    trainer: TrainerOptions = field(default_factory=TrainerOptions)
    logger: Any = None
    callbacks: Any = None
    optim: Any = MISSING  # a _partial_ optimiser (conf/optim)
    scheduler: Any = MISSING  # a _partial_ schedule (conf/scheduler)
    module: Any = MISSING  # the LightningModule's _target_ and arguments
    loss: LossOptions = field(default_factory=LossOptions)
    export: ExportStepOptions = field(default_factory=ExportStepOptions)
    metrics: MetricsOptions = field(default_factory=MetricsOptions)
    out_dir: str = MISSING
    hydra_dir: str = MISSING
    checkpoint_dir: str = MISSING
    ckpt_path: str | None = None
    # samples per optimiser step over every device and node; set: trainer.accumulate_grad_batches follows from it
    # (fastflow3d.training.trainer.settle_batch); null: data.batch_size x accumulation x devices x nodes as configured
    effective_batch: int | None = setting(None, "count")
    overwrite: bool = False
    seed: int = 0
    compile: bool = False


@dataclass
class ExportOptions:
    """``export.py`` (``conf/export.yaml``)."""

    checkpoint: str = MISSING
    format: str = "all"  # onnx, pt2, all or a comma-separated list
    int8: Any = False  # true (calibrated on the run's data.train) or a label.py out_dir: also fastflow3d.int8.onnx
    out_dir: str | None = None
    hydra_dir: str = MISSING  # each launch's config and log (conf/hydra/default.yaml); unset: outputs/hydra/<script>


def register() -> None:
    """Store ``train_schema`` and ``export_schema`` in Hydra's ConfigStore. Idempotent; ``train.py`` and
    ``export.py`` call it before Hydra composes, and so must a caller of Hydra's compose API."""
    store("train_schema", TrainOptions)
    store("export_schema", ExportOptions)
