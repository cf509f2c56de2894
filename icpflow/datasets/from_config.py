"""Readers from a Hydra run config (``conf/dataset/*.yaml`` composed into label.py's or eval.py's config).

``open_dataset(cfg, horizon)`` instantiates ``cfg.dataset.reader`` for pairs (t, t + horizon): readers that take
``max_horizon`` (synthetic, av2, kitti, sequence: their samples are the scans t for which t + max_horizon exists)
get it raised to ``horizon``; the others must reach it themselves (waymo/nuscenes: their frame count). A missing or
empty root, a reader's own error, no samples or a horizon the reader cannot give raise one-line
:class:`DatasetError`.
"""

from __future__ import annotations

import inspect
from pathlib import Path

from omegaconf import DictConfig, OmegaConf, open_dict

from icpflow.core.deprecation import MOVED_TARGETS, current_target
from icpflow.core.stops import raise_stop_behind


class DatasetError(ValueError):
    """The configured dataset cannot be opened. The message is one line."""


def dataset_root(cfg: DictConfig) -> str | None:
    """``dataset.root`` as an absolute path, None when the reader reads no files; DatasetError when it is unset."""
    name = cfg.dataset.name
    root = "???" if OmegaConf.is_missing(cfg.dataset, "root") else cfg.dataset.get("root", None)
    if root == "???":
        raise DatasetError(f"dataset {name}: dataset.root is not set (pass dataset.root=/path/to/{name})")
    return None if root is None else str(Path(root).expanduser().resolve())


def raise_max_horizon(cfg: DictConfig, horizon: int) -> bool:
    """Raise ``cfg.dataset.reader.max_horizon`` to ``horizon`` for readers that take it; True if raised (a larger
    value set by the user is kept)."""
    from hydra.utils import get_class

    reader = cfg.dataset.reader
    try:
        takes = "max_horizon" in inspect.signature(get_class(reader_config(reader)._target_)).parameters
    except Exception as error:  # an unimportable reader: opening it reports why
        raise_stop_behind(error)
        return False
    if not takes or int(reader.get("max_horizon") or 1) >= horizon:
        return False
    with open_dict(reader):
        reader.max_horizon = horizon
    return True


def reader_config(reader: DictConfig) -> DictConfig:
    """``dataset.reader`` with its ``_target_`` named by today's path where the reader's module moved (a config of
    the last release: ``icpflow.core.deprecation.MOVED_TARGETS``), so that it opens without the old path's warning."""
    target = current_target(reader.get("_target_"), MOVED_TARGETS)
    if target != reader.get("_target_"):
        with open_dict(reader):
            reader._target_ = target  # in place: the run's config names today's path from here on
    return reader


def open_dataset(cfg: DictConfig, horizon: int = 1):
    """The reader of ``cfg.dataset`` for pairs (t, t + ``horizon``) (see the module docstring)."""
    from hydra.utils import instantiate

    name = cfg.dataset.name
    root = dataset_root(cfg)
    if root is not None:
        path = Path(root)
        if not path.is_dir():
            raise DatasetError(f"dataset {name}: root {path} does not exist or is not a directory")
        if not any(path.iterdir()):
            raise DatasetError(f"dataset {name}: root {path} is empty")
    raised = raise_max_horizon(cfg, horizon)
    try:
        dataset = instantiate(reader_config(cfg.dataset.reader))
    except Exception as error:  # hydra wraps the reader's own one-line error
        raise_stop_behind(error)
        cause = error.__cause__ or error
        text = str(cause).splitlines()[0] if str(cause) else type(cause).__name__
        raise DatasetError(
            f"dataset {name}: {text}" + (f" (with dataset.reader.max_horizon={horizon})" if raised else "")
        ) from None
    if len(dataset) == 0:
        why = dataset.why_empty() if hasattr(dataset, "why_empty") else ""
        raise DatasetError(
            f"dataset {name}: no samples under {root} (split {cfg.split})"
            + (f": {why} (horizon={horizon})" if why else "")
        )
    if horizon > dataset.max_horizon:
        raise DatasetError(f"dataset {name}: horizon={horizon} exceeds its max_horizon {dataset.max_horizon}")
    return dataset
