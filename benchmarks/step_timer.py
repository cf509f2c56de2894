"""A Lightning callback for ``bench_training_step``: the wall-clock time at the end of every training batch, written
as JSON (``{"ends": [seconds, ...]}``) when training ends. Loaded by ``train.py`` of any tree through
``+callbacks.step_timer._target_=benchmarks.step_timer.StepTimer`` with this checkout on PYTHONPATH."""

import json
import time
from pathlib import Path

import lightning as L


class StepTimer(L.Callback):
    """Records ``time.perf_counter()`` after each training batch; writes them to ``path`` at the end of training."""

    def __init__(self, path: str):
        self.path = Path(path)
        self.ends: list[float] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.ends.append(time.perf_counter())

    def on_train_end(self, trainer, pl_module) -> None:
        self.path.write_text(json.dumps({"ends": self.ends}))
