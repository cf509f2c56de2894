"""``train.py``: from the Hydra config (``conf/train.yaml``) to a Lightning fit of the student on pseudo-flow shards.

Everything a run writes lands under ``out_dir``: ``checkpoints/`` (best on validation dynamic EPE and
``last.ckpt``), ``tensorboard/``, ``bev/`` and ``hydra/``. ``ckpt_path=last`` resumes from
``<checkpoint_dir>/last.ckpt`` (optimiser, schedule and step count included); any other value is a checkpoint file.
"""

from __future__ import annotations

from pathlib import Path

import lightning as L
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from fastflow3d.data import DataError, ShardDataModule, StudentDataset
from fastflow3d.module import StudentModule


class TrainError(RuntimeError):
    """A training run cannot start. The message is one line."""


def check_data(cfg: DictConfig) -> None:
    """Both shard directories hold samples (else one line saying how to create them); supervised needs gt."""
    for key, split in (("train", "train"), ("val", "val")):
        path = cfg.data[key]
        try:
            dataset = StudentDataset(path)
        except DataError as error:
            raise TrainError(f"data.{key}: {error}; label a dataset into it first, e.g. "
                             f"`python label.py split={split} out_dir={path}`") from None
        if key == "train" and cfg.loss.name == "supervised" and "gt" not in dataset[0]:
            raise TrainError(f"loss.name=supervised needs ground truth, but data.train={path} has none")


def resolve_ckpt_path(cfg: DictConfig) -> str | None:
    """The checkpoint to resume from: None, ``<checkpoint_dir>/last.ckpt`` for ``last``, or the given file."""
    value = cfg.get("ckpt_path")
    if not value:
        return None
    path = Path(cfg.checkpoint_dir) / "last.ckpt" if value == "last" else Path(value)
    if not path.is_file():
        raise TrainError(f"ckpt_path={value}: {path} does not exist (nothing to resume; leave ckpt_path unset to "
                         "start afresh)")
    return str(path)


def build_trainer(cfg: DictConfig) -> L.Trainer:
    """The Lightning Trainer of ``cfg.trainer`` (Trainer keyword arguments) with the configured logger and callbacks."""
    logger = instantiate(cfg.logger) if cfg.get("logger") else False
    callbacks = [instantiate(callback) for callback in (cfg.get("callbacks") or {}).values()]
    trainer_kwargs = OmegaConf.to_container(cfg.trainer, resolve=True)
    return L.Trainer(**trainer_kwargs, logger=logger, callbacks=callbacks, default_root_dir=cfg.out_dir)


def fit(cfg: DictConfig) -> L.Trainer:
    """Train the student as ``cfg`` says; returns the Trainer after ``fit`` (raises TrainError if it cannot start)."""
    check_data(cfg)
    ckpt_path = resolve_ckpt_path(cfg)
    plain = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    module = StudentModule(plain)
    if cfg.compile:
        module.model.compile(dynamic=True)
    datamodule = ShardDataModule(**plain["data"])
    trainer = build_trainer(cfg)
    trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt_path, weights_only=True)
    return trainer
