"""A callback for tests of data-parallel training (``tests/fastflow3d/training/test_ddp.py``), added to a train.py run
with
``+callbacks.record._target_=helpers.ddp.RecordSamples +callbacks.record.folder=<dir>``."""

import json
import os
import signal
from pathlib import Path

from lightning.pytorch.callbacks import Callback


class RecordSamples(Callback):
    """Each rank appends ``{"epoch", "step", "samples", "pid"}`` per training batch to ``<folder>/rank<r>.jsonl``; with
    ``sigterm_at_step``, rank 0 sends itself SIGTERM (a scheduler's pre-emption of the launcher) before that step."""

    def __init__(self, folder, sigterm_at_step: int | None = None):
        self.folder = Path(folder)
        self.sigterm_at_step = sigterm_at_step

    def on_train_batch_start(self, trainer, pl_module, batch, index) -> None:
        if trainer.global_rank == 0 and trainer.global_step == self.sigterm_at_step:
            os.kill(os.getpid(), signal.SIGTERM)
        self.folder.mkdir(parents=True, exist_ok=True)
        record = {
            "epoch": trainer.current_epoch,
            "step": trainer.global_step,
            "samples": list(batch["sample_id"]),
            "pid": os.getpid(),
        }
        with open(self.folder / f"rank{trainer.global_rank}.jsonl", "a") as handle:
            handle.write(json.dumps(record) + "\n")
