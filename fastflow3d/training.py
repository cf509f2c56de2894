"""``train.py``: from the Hydra config (``conf/train.yaml``) to a Lightning fit of the student on pseudo-flow shards,
ending with the export of the best checkpoint.

Everything a run writes lands under ``out_dir``: ``checkpoints/`` (best on validation dynamic EPE and
``last.ckpt``), ``tensorboard/``, ``bev/``, ``export/`` and ``hydra/``. ``ckpt_path=last`` resumes from
``<checkpoint_dir>/last.ckpt`` (optimiser, schedule and step count included); any other value is a checkpoint file.
The saved config's ``data.teacher`` holds the teacher's ground and ego-motion settings (``TEACHER_FIELDS`` of
``fastflow3d.data``) that the Predictor uses on raw scans.
"""

from __future__ import annotations

import logging
from pathlib import Path

import lightning as L
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from fastflow3d.artifact import FORMATS
from fastflow3d.checkpoint import CheckpointError, read_checkpoint
from fastflow3d.data import TEACHER_FIELDS, DataError, ShardDataModule, StudentDataset, labeller_teacher
from fastflow3d.export import export_checkpoint
from fastflow3d.module import StudentModule
from icpflow.shards.verify import ShardError

log = logging.getLogger(__name__)


class TrainError(RuntimeError):
    """A training run cannot start, or its final export failed. The message is one line."""


def check_data(cfg: DictConfig) -> None:
    """Both shard directories hold samples (else one line saying how to create them), every shard they list is
    complete and valid (else one line naming it: the checks ``label.py`` makes before it skips a shard);
    supervised needs gt."""
    for key, split in (("train", "train"), ("val", "val")):
        path = cfg.data[key]
        try:
            dataset = StudentDataset(path)
        except DataError as error:
            raise TrainError(
                f"data.{key}: {error}; label a dataset into it first, e.g. "
                f"`python label.py split={split} out_dir={path}`"
            ) from None
        try:
            dataset.shards.verify()
        except ShardError as error:
            raise TrainError(
                f"data.{key}: {error}; rerun the label.py command that wrote it (same out_dir={path}): "
                "it redoes damaged shards"
            ) from None
        if key == "train" and cfg.loss.name == "supervised" and "gt" not in dataset[0]:
            raise TrainError(f"loss.name=supervised needs ground truth, but data.train={path} has none")


def inference_teacher(cfg: DictConfig) -> dict:
    """The teacher settings saved with the model (``TEACHER_FIELDS`` -> value): ``data.teacher`` (an optional
    ``preset``, then fields) or, when it is null, the settings of the teacher that labelled ``data.train``."""
    from icpflow.teacher.config import ICPFlowConfig

    given = cfg.data.get("teacher")
    if given is None:
        source, values = f"data.train={cfg.data.train}", labeller_teacher(cfg.data.train)
        if values is None:
            raise TrainError(
                f"data.teacher is null and the shards of data.train={cfg.data.train} carry no teacher "
                "config; set it, e.g. data.teacher={preset:waymo}"
            )
        values = {key: values[key] for key in TEACHER_FIELDS if key in values}
    elif not OmegaConf.is_dict(given):
        raise TrainError(f"data.teacher must be null or a dict of preset and ICPFlowConfig fields, got {given!r}")
    else:
        source, values = "data.teacher", OmegaConf.to_container(given, resolve=True)
        unknown = sorted(set(values) - {"preset", *TEACHER_FIELDS})
        if unknown:
            raise TrainError(
                f"data.teacher: {', '.join(unknown)} not used at inference; give preset and/or "
                f"{', '.join(TEACHER_FIELDS)}"
            )
    preset = values.pop("preset", None)
    try:
        teacher = ICPFlowConfig.preset(preset, **values) if preset else ICPFlowConfig(**values)
    except ValueError as error:
        raise TrainError(f"{source}: {error}") from None
    return {key: getattr(teacher, key) for key in TEACHER_FIELDS}


def resolve_ckpt_path(cfg: DictConfig) -> str | None:
    """The checkpoint to resume from: None, ``<checkpoint_dir>/last.ckpt`` for ``last``, or the given file."""
    value = cfg.get("ckpt_path")
    if not value:
        return None
    path = Path(cfg.checkpoint_dir) / "last.ckpt" if value == "last" else Path(value)
    if not path.is_file():
        raise TrainError(
            f"ckpt_path={value}: {path} does not exist (nothing to resume; leave ckpt_path unset to start afresh)"
        )
    try:
        read_checkpoint(path)
    except CheckpointError as error:
        raise TrainError(
            f"ckpt_path={value}: {error}; give another checkpoint, or leave ckpt_path unset to start afresh"
        ) from None
    return str(path)


def export_formats(cfg: DictConfig) -> tuple[str, ...]:
    """``export.formats`` checked before training (an unknown name would otherwise fail only at the end)."""
    formats = tuple(cfg.export.formats or ())
    unknown = [name for name in formats if name not in FORMATS]
    if unknown:
        raise TrainError(
            f"export.formats: unknown {', '.join(map(str, unknown))}; use a list of "
            f"{', '.join(FORMATS)}, or [] for no export"
        )
    return formats


def build_trainer(cfg: DictConfig) -> L.Trainer:
    """The Lightning Trainer of ``cfg.trainer`` (Trainer keyword arguments) with the configured logger and callbacks."""
    logger = instantiate(cfg.logger) if cfg.get("logger") else False
    callbacks = [instantiate(callback) for callback in (cfg.get("callbacks") or {}).values()]
    trainer_kwargs = OmegaConf.to_container(cfg.trainer, resolve=True)
    return L.Trainer(**trainer_kwargs, logger=logger, callbacks=callbacks, default_root_dir=cfg.out_dir)


def export_best(trainer: L.Trainer, cfg: DictConfig, formats: tuple[str, ...]) -> Path | None:
    """Export the best checkpoint (``last.ckpt`` when there is none, with a warning) to ``export.dir``; returns the
    directory, or None when there is nothing to do (no formats, fast_dev_run, interrupted run, not rank 0)."""
    if not formats or trainer.fast_dev_run or trainer.interrupted or not trainer.is_global_zero:
        return None
    best = trainer.checkpoint_callback.best_model_path if trainer.checkpoint_callback else ""
    source = Path(best) if best and Path(best).is_file() else Path(cfg.checkpoint_dir) / "last.ckpt"
    if not source.is_file():
        raise TrainError(f"training ended with no checkpoint to export in {cfg.checkpoint_dir}")
    if source.name == "last.ckpt":
        log.warning("no best checkpoint (no validation ran?): exporting %s instead", source)
    try:
        out_dir = export_checkpoint(source, cfg.export.dir, formats)
    except (ValueError, RuntimeError, OSError) as error:
        raise TrainError(
            f"training finished but exporting {source} failed: {' '.join(str(error).split())} "
            f"(retry with `python export.py checkpoint={source}`)"
        ) from None
    log.info("exported %s (%s) to %s", source.name, ", ".join(formats), out_dir)
    return out_dir


def fit(cfg: DictConfig) -> L.Trainer:
    """Train the student as ``cfg`` says, then export its best checkpoint; returns the Trainer after ``fit``
    (raises TrainError if it cannot start or the export fails)."""
    check_data(cfg)
    ckpt_path = resolve_ckpt_path(cfg)
    formats = export_formats(cfg)
    plain = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
    plain["data"]["teacher"] = inference_teacher(cfg)
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    module = StudentModule(plain)
    if cfg.compile:
        module.model.compile(dynamic=True)
    data = plain["data"]
    datamodule = ShardDataModule.from_config(data, module.model.grid)
    trainer = build_trainer(cfg)
    trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt_path, weights_only=True)
    export_best(trainer, cfg, formats)
    return trainer
