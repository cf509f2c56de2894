"""Lightning callbacks and checkpoint writing of the training stage: ``last.ckpt`` kept current (and a clean stop on
SIGTERM/SIGINT, through ``icpflow.core.errors_and_signals.on_signals``), one best checkpoint after a resume (through
ModelCheckpoint's public ``state_dict`` / ``load_state_dict``), atomic checkpoint files, and a final validation."""

from __future__ import annotations

import io
import logging
import signal
from pathlib import Path

import lightning as L
import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO
from lightning.pytorch.callbacks import Checkpoint, ModelCheckpoint

from icpflow.core.atomic import atomic_path
from icpflow.core.errors_and_signals import Stop, on_signals, signal_words
from icpflow.core.stops import raise_stop_behind

log = logging.getLogger(__name__)


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning's checkpoint writer through ``icpflow.core.atomic``: the checkpoint is serialised in memory, then
    written under a temporary name in its own folder and renamed, so a full disk or a kill never leaves a half-written
    ``.ckpt`` (Lightning's own writer moves a file from the system's temporary folder), and a write error is one
    ``icpflow.core.atomic.WriteError`` naming the checkpoint."""

    def save_checkpoint(self, checkpoint: dict, path, storage_options=None) -> None:
        buffer = io.BytesIO()
        torch.save(checkpoint, buffer)
        with atomic_path(path, make_parents=True) as tmp:
            tmp.write_bytes(buffer.getbuffer())


class TrainingStopped(Stop):
    """A signal stopped the training loop; ``last.ckpt`` holds the state it stopped at (the message says so)."""


def _nothing() -> None:
    pass


class LastCheckpoint(Checkpoint):
    """Keep ``<dirpath>/last.ckpt`` at the latest state: after every validation and when training ends; stop cleanly
    on SIGTERM or SIGINT.

    (Lightning's ModelCheckpoint refreshes ``last.ckpt`` only when it also saves a top-k checkpoint, so it can lag
    behind.) A ``Checkpoint`` subclass, so Lightning runs it after the other checkpoint callbacks (those listed
    before it): ``last.ckpt`` then holds their state after the same validation (which best checkpoint exists), and a
    resume keeps exactly one best checkpoint. Files are written atomically (:class:`AtomicCheckpointIO`).

    Signals: from the start of the training loop to its end, a SIGTERM (a scheduler's pre-emption, ``scancel``) or
    a SIGINT (Ctrl-C) lets the current step (or validation) finish; then ``last.ckpt`` is saved at that step and
    :class:`TrainingStopped` is raised (every rank stops at the same step). A second signal stops at once
    (``icpflow.core.errors_and_signals.Stop``). The handlers are installed by
    ``icpflow.core.errors_and_signals.on_signals``, as every entry point's. On a resume (``ckpt_path``), best
    checkpoints in the folder that the restored state does not know (written by a run killed between the two saves, or
    by older versions) are weighed by the score they hold: the best ``save_top_k`` are kept, the others removed.
    """

    def __init__(self, dirpath):
        self.path = Path(dirpath) / "last.ckpt"
        self.saved_step = -1
        self.signum: int | None = None
        # puts back the handlers on_train_start replaced (icpflow.core.errors_and_signals.on_signals)
        self._restore = _nothing

    # -------------------------------------------------------------------------------------------- last.ckpt

    def _save(self, trainer: L.Trainer) -> None:
        if trainer.fast_dev_run or trainer.sanity_checking or trainer.global_step == self.saved_step:
            return
        trainer.save_checkpoint(self.path, weights_only=False)  # rank 0 writes (AtomicCheckpointIO)
        trainer.strategy.barrier("LastCheckpoint")
        self.saved_step = trainer.global_step

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._save(trainer)
        self._stop_if_asked(trainer)

    def on_train_batch_end(self, trainer: L.Trainer, pl_module: L.LightningModule, outputs, batch, index) -> None:
        self._stop_if_asked(trainer)

    def on_train_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._restore_handlers()
        self._save(trainer)

    # -------------------------------------------------------------------------------------------- signals

    def _note(self, signum: int) -> None:
        if self.signum is not None:  # asked twice: stop now
            raise Stop(signum)
        self.signum = signum

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if trainer.ckpt_path:
            keep_best_after_resume(trainer)
        self.signum = None
        self._restore_handlers()
        self._restore = on_signals(self._note)

    def _restore_handlers(self) -> None:
        restore, self._restore = self._restore, _nothing
        restore()

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        self._restore_handlers()

    def _stop_if_asked(self, trainer: L.Trainer) -> None:
        if trainer.sanity_checking:
            return
        asked = self.signum is not None
        if trainer.world_size > 1:  # all ranks stop at the same step
            asked = trainer.strategy.reduce_boolean_decision(asked, all=False)
        if not asked:
            return
        signum = self.signum or signal.SIGTERM
        self._save(trainer)
        if self.saved_step == trainer.global_step and not trainer.fast_dev_run:
            kept = f"saved {self.path}; to resume, rerun the same command with ckpt_path=last"
        else:
            kept = "nothing saved (fast_dev_run)"
        raise TrainingStopped(signum, f"{signal_words(signum)} at step {trainer.global_step}: {kept}")


def _stored_score(path: Path, state_key: str) -> float | None:
    """The monitored score a ModelCheckpoint recorded in a checkpoint file it wrote (None: unreadable or not its)."""
    try:
        checkpoint = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
        score = checkpoint["callbacks"][state_key]["current_score"]
        return float(score)
    except Exception as error:  # a damaged or foreign file: left alone
        raise_stop_behind(error)
        return None


def keep_best_after_resume(trainer: L.Trainer) -> None:
    """After a resume: every ModelCheckpoint with a monitor keeps its best ``save_top_k`` of the checkpoints it
    knows (restored state) and of the files in its folder that match its file name but that state does not know;
    the others are removed (rank 0) and its state says which are kept (:func:`set_best_checkpoints`)."""
    for callback in trainer.checkpoint_callbacks:
        if not isinstance(callback, ModelCheckpoint) or not callback.monitor or callback.save_top_k < 1:
            continue
        prefix = (callback.filename or "").split("{")[0]
        if not prefix or not callback.dirpath or not Path(callback.dirpath).is_dir():
            continue
        best = callback.state_dict()["best_k_models"]
        known = {str(path): float(score) for path, score in best.items() if Path(path).is_file()}
        for path in sorted(Path(callback.dirpath).glob(f"{prefix}*{callback.FILE_EXTENSION}")):
            if str(path) not in known and path.name != "last.ckpt":
                score = _stored_score(path, callback.state_key)
                if score is not None:
                    known[str(path)] = score
        if len(known) == len(best) and set(known) == set(best):
            continue
        ranked = sorted(known.items(), key=lambda item: item[1], reverse=callback.mode == "max")
        kept, dropped = ranked[: callback.save_top_k], ranked[callback.save_top_k :]
        if trainer.is_global_zero:
            for path, _ in dropped:
                Path(path).unlink(missing_ok=True)
            if dropped:
                log.warning(
                    "resume: kept %s; removed %s (worse %s)",
                    ", ".join(Path(path).name for path, _ in kept),
                    ", ".join(Path(path).name for path, _ in dropped),
                    callback.monitor,
                )
        trainer.strategy.barrier("keep_best_after_resume")
        set_best_checkpoints(callback, kept)


#: the keys of ModelCheckpoint's state (``state_dict()``, stored in every checkpoint) that name its best files
BEST_STATE_KEYS = ("best_k_models", "best_model_path", "best_model_score", "kth_best_model_path", "kth_value")


def set_best_checkpoints(callback: ModelCheckpoint, kept: list[tuple[str, float]]) -> None:
    """Make ``callback`` know exactly the best checkpoints ``kept`` (``(path, score)``, best first), through its
    public ``state_dict()`` / ``load_state_dict()`` (the state Lightning saves in and restores from a checkpoint):
    the keys :data:`BEST_STATE_KEYS`. Lightning keeps these keys for old checkpoints to load;
    ``tests/fastflow3d/training/test_faults_training.py`` fails if a Lightning version stops restoring them. With
    nothing kept, only
    ``best_k_models`` changes (the best path and score stay as restored)."""
    state = {**callback.state_dict(), "best_k_models": {path: torch.tensor(score) for path, score in kept}}
    if kept:
        state["best_model_path"], state["best_model_score"] = kept[0][0], torch.tensor(kept[0][1])
        state["kth_best_model_path"], state["kth_value"] = kept[-1][0], torch.tensor(kept[-1][1])
    callback.load_state_dict(state)


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
