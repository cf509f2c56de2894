"""Tiny trained FastFlow3D checkpoints (of ``helpers.training.TINY_MODEL``) for the export, inference and evaluation
tests; the one trained once per session is conftest.py's ``tiny_student``."""

from __future__ import annotations

import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np
import torch

from helpers.shards import write_pseudo_labels
from helpers.training import TINY_MODEL, tiny_model_overrides, train_cfg


def tiny_checkpoint(
    path,
    pair,
    steps: int,
    keep0=None,
    keep1=None,
    options: dict | None = None,
    remove_ground: bool = False,
) -> Path:
    """A training checkpoint of the tiny FastFlow3D (``TINY_MODEL`` with the model ``options`` changed) made by
    ``train.py``'s own code (``fastflow3d.training.trainer.fit``): ``steps`` (>= 1) Adam steps on one shard, in
    ``label.py``'s layout, whose pseudo-labels are ``pair``'s true flow (on the rows ``keep0`` / ``keep1`` of its
    scans, all by default), so that its weights and BatchNorm statistics are not the initial ones; the run's
    ``last.ckpt``, moved to ``path`` (its stored run folders are ``path``'s folder: :func:`place_checkpoint`).

    ``remove_ground``: the student sees the non-ground points only (``data.remove_ground``; off: every point, so
    that a test's eager reference runs the network on the whole scans). Returns ``path``."""
    from fastflow3d.training.trainer import fit

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f"{path.stem}-run-", dir=path.parent))
    keep0 = np.arange(len(pair.pc0)) if keep0 is None else keep0
    keep1 = np.arange(len(pair.pc1)) if keep1 is None else keep1
    labels = write_pseudo_labels(work / "labels", [rows_of(pair, keep0, keep1)])
    cfg = train_cfg(
        work,
        labels,
        labels,
        *tiny_model_overrides(**(options or {})),
        f"trainer.max_steps={steps}",
        "trainer.precision=32-true",
        "trainer.num_sanity_val_steps=0",
        "optim.lr=2e-3",
        "scheduler=constant",
        "loss.weighting=uniform",
        "data.augment=null",
        "data.batch_size=1",
        f"data.remove_ground={str(remove_ground).lower()}",
        "~logger",
        "~callbacks.lr_monitor",
        "metrics.bev_every=0",
    )
    assert cfg.model._target_ == TINY_MODEL["_target_"]
    torch.manual_seed(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Lightning's advice for real runs (few batches, workers)
        fit(cfg)
    return place_checkpoint(work / "run" / "checkpoints" / "last.ckpt", path)


def place_checkpoint(source, path, stored: dict | None = None) -> Path:
    """``source`` (a training checkpoint) copied to ``path``, its stored run folders set to ``path``'s folder (as if
    the run had been there: the export goes to ``<path's folder>/export``), then the entries ``stored`` of its saved
    config replaced (a checkpoint that claims another run's folders, as a downloaded one may). Returns ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if Path(source) != path:
        shutil.copyfile(source, path)
    moved = {
        "out_dir": str(path.parent),
        "checkpoint_dir": str(path.parent),
        "export": {"dir": str(path.parent / "export")},
    }
    checkpoint = torch.load(path, weights_only=True)
    checkpoint["hyper_parameters"]["cfg"].update({**moved, **(stored or {})})
    torch.save(checkpoint, path)
    return path


def tiny_network(**options):
    """The tiny FastFlow3D (``TINY_MODEL`` with ``options`` changed) as built from its config, initial weights."""
    from fastflow3d.network.model import FastFlow3D

    return FastFlow3D(**{key: value for key, value in {**TINY_MODEL, **options}.items() if key != "_target_"})


def rows_of(pair, keep0, keep1):
    """``pair`` cut to the rows ``keep0`` of pc0 (and its per-point arrays) and ``keep1`` of pc1."""
    import dataclasses

    per0 = ("pc0", "ground0", "time0", "flow", "flow_valid", "classes", "instance", "dynamic")
    per1 = ("pc1", "ground1", "time1")
    changes = {name: getattr(pair, name)[keep0] for name in per0 if getattr(pair, name) is not None}
    changes.update({name: getattr(pair, name)[keep1] for name in per1 if getattr(pair, name) is not None})
    return dataclasses.replace(pair, **changes)
