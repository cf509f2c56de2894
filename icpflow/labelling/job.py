"""What a labelling run is given (:class:`LabelJob`) and how it fails (:class:`LabelError`); how it stops on a signal
is ``icpflow.core.errors_and_signals.Stop`` (``icpflow.labelling.cli``)."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path


def config_hash(config_yaml: str) -> str:
    """Short stable hash of the labeller config text."""
    return hashlib.sha256(config_yaml.encode()).hexdigest()[:16]


class LabelError(RuntimeError):
    """A labelling run cannot start or go on (config mismatch, bad option, a worker died outside a sample).
    The message is one line."""


@dataclass
class LabelJob:
    """Everything a worker needs to label a sample (picklable): dataset, teacher config, output settings and the
    ``labeller`` (None: the teacher; else its spec, ``icpflow.labelling.labeller.identity``)."""

    dataset: object
    teacher_cfg: object
    out_dir: Path
    config_yaml: str
    horizon: int = 1
    tracker: bool = False
    compression: str | None = None
    labeller: dict | None = None
    hash: str = field(init=False)

    def __post_init__(self):
        self.out_dir = Path(self.out_dir)
        self.hash = config_hash(self.config_yaml)
