"""Lightning callbacks of the training stage: ``last.ckpt`` kept current, and a final validation."""

from __future__ import annotations

import logging
from contextlib import nullcontext
from pathlib import Path

import lightning as L

from icpflow.atomic import atomic_path


class LastCheckpoint(L.Callback):
    """Keep ``<dirpath>/last.ckpt`` at the latest state: after every validation and when training ends.

    (Lightning's ModelCheckpoint refreshes ``last.ckpt`` only when it also saves a top-k checkpoint, so it can lag
    behind.) The file is written atomically (``icpflow.atomic``), so a crash never leaves it half-written.
    """

    def __init__(self, dirpath):
        self.path = Path(dirpath) / "last.ckpt"
        self.saved_step = -1

    def _save(self, trainer: L.Trainer) -> None:
        if trainer.fast_dev_run or trainer.sanity_checking or trainer.global_step == self.saved_step:
            return
        # every rank takes part in save_checkpoint; the strategy writes on rank 0 only, which renames it in place
        target = atomic_path(self.path, make_parents=True) if trainer.is_global_zero else nullcontext(self.path)
        with target as path:
            trainer.save_checkpoint(path, weights_only=False)
        trainer.strategy.barrier("LastCheckpoint")
        self.saved_step = trainer.global_step

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._save(trainer)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._save(trainer)


class ValidateAtEnd(L.Callback):
    """Validate after the last training batch when the schedule would not (so a best checkpoint always exists).

    A run that stops at ``max_steps`` (or at the end of ``max_epochs`` with step-based validation) between two
    scheduled validations ends unvalidated. On the batch that ends training this asks Lightning to stop
    (``trainer.should_stop``), which makes its loop run validation right after that batch; a batch that is a
    scheduled validation point is validated once, not twice. Validation gated by ``check_val_every_n_epoch`` stays
    gated (an epoch that is not a validation epoch is not validated).
    """

    def on_train_batch_end(
        self, trainer: L.Trainer, pl_module: L.LightningModule, outputs, batch, batch_idx: int
    ) -> None:
        if trainer.fast_dev_run:
            return
        loop = trainer.fit_loop
        last_step = 0 < trainer.max_steps <= trainer.global_step
        last_epoch = loop.max_epochs is not None and 0 < loop.max_epochs <= trainer.current_epoch + 1
        if last_step or (last_epoch and loop.epoch_loop.batch_progress.is_last_batch):
            trainer.should_stop = True


def progress_bar() -> L.Callback:
    """Lightning's progress bar (rich when installed, as Lightning picks it) whose training description is
    ``Epoch N``, plus ``/last`` only when ``max_epochs`` bounds the run (Lightning's rich bar shows ``Epoch 4/-2``
    for the unbounded ``max_epochs=-1`` of step-based recipes)."""
    from lightning.pytorch.callbacks import RichProgressBar, TQDMProgressBar
    from lightning.pytorch.utilities.imports import _RICH_AVAILABLE

    if not _RICH_AVAILABLE:
        return TQDMProgressBar()  # its description is "Epoch N" already

    class EpochProgressBar(RichProgressBar):
        def _get_train_description(self, current_epoch: int) -> str:
            bounded = self.trainer.max_epochs is not None and self.trainer.max_epochs > 0
            description = f"Epoch {current_epoch}" + (f"/{self.trainer.max_epochs - 1}" if bounded else "")
            return f"{description:{len(self.validation_description)}}"

    return EpochProgressBar()


class ModelSize(L.Callback):
    """One line when fitting starts: the network's class and its parameter count (in place of Lightning's model
    summary table, whose FLOPs column reads 0 for this network: its pillar scatter runs outside the counter)."""

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.is_global_zero:
            model = getattr(pl_module, "model", pl_module)
            count = sum(p.numel() for p in model.parameters())
            trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
            logging.getLogger("fastflow3d.training").info(
                "%s: %.2f M parameters (%.2f M trainable)", type(model).__name__, count / 1e6, trainable / 1e6
            )
