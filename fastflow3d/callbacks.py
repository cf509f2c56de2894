"""Lightning callbacks of the training stage."""

from __future__ import annotations

import os
from pathlib import Path

import lightning as L


class LastCheckpoint(L.Callback):
    """Keep ``<dirpath>/last.ckpt`` at the latest state: after every validation and when training ends.

    (Lightning's ModelCheckpoint refreshes ``last.ckpt`` only when it also saves a top-k checkpoint, so it can lag
    behind.) The file is written under a temporary name and renamed, so a crash never leaves it half-written.
    """

    def __init__(self, dirpath):
        self.path = Path(dirpath) / "last.ckpt"
        self.saved_step = -1

    def _save(self, trainer: L.Trainer) -> None:
        if trainer.fast_dev_run or trainer.sanity_checking or trainer.global_step == self.saved_step:
            return
        tmp = self.path.with_name(self.path.name + ".tmp")
        if trainer.is_global_zero:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        trainer.save_checkpoint(tmp, weights_only=False)  # every rank takes part; the strategy writes on rank 0
        if trainer.is_global_zero:
            os.replace(tmp, self.path)
        trainer.strategy.barrier("LastCheckpoint")
        self.saved_step = trainer.global_step

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._save(trainer)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._save(trainer)
