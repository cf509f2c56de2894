"""Tiny trained FastFlow3D checkpoints for the export, inference and evaluation tests."""

from __future__ import annotations

import dataclasses
import json
import tempfile
import warnings
from pathlib import Path

import numpy as np
import torch

from helpers.shards import write_pseudo_labels
from helpers.training import train_cfg


def tiny_model(half_width: float, cell: float) -> dict:
    """The config (``conf/model`` form) of a tiny FastFlow3D over ``[-half_width, half_width]^2`` m with ``cell``
    m pillars: 8 pillar channels, encoders of 8 / 16 / 32 channels with one extra conv each."""
    return {
        "_target_": "fastflow3d.network.model.FastFlow3D",
        "x_range": [-half_width, half_width],
        "y_range": [-half_width, half_width],
        "z_range": [-3.0, 3.0],
        "cell": cell,
        "pillar_channels": 8,
        "stage_channels": [8, 16, 32],
        "stage_blocks": [1, 1, 1],
    }


def tiny_checkpoint(
    path,
    model_cfg: dict,
    pair,
    steps: int,
    keep0=None,
    keep1=None,
    stored: dict | None = None,
    remove_ground: bool = False,
) -> Path:
    """A training checkpoint of the FastFlow3D of ``model_cfg`` made by ``train.py``'s own code
    (``fastflow3d.training.trainer.fit``): ``steps`` (>= 1) Adam steps on one shard, in ``label.py``'s layout, whose
    pseudo-labels are ``pair``'s true flow (on the rows ``keep0`` / ``keep1`` of its scans, all by default), so
    that its weights and BatchNorm statistics are not the initial ones; the run's ``last.ckpt``, moved to ``path``.

    The run lives in a folder beside ``path``; the checkpoint's stored run folders are set to ``path``'s folder (as
    if the run had been there: the export goes to ``<path's folder>/export``). ``stored``: entries of the saved
    config replaced afterwards (a checkpoint that claims another run's folders, as a downloaded one may).
    ``remove_ground``: the student sees the non-ground points only (``data.remove_ground``; off: every point, so
    that a test's eager reference runs the network on the whole scans). Returns ``path``."""
    from fastflow3d.training.trainer import fit

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f"{path.stem}-run-", dir=path.parent))
    keep0 = np.arange(len(pair.pc0)) if keep0 is None else keep0
    keep1 = np.arange(len(pair.pc1)) if keep1 is None else keep1
    labels = write_pseudo_labels(work / "labels", [rows_of(pair, keep0, keep1)])
    model = {**TINY_DEFAULTS, **{key: value for key, value in model_cfg.items() if key != "_target_"}}
    cfg = train_cfg(
        work,
        labels,
        labels,
        *(f"model.{key}={json.dumps(value)}" for key, value in model.items()),
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
    torch.manual_seed(0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Lightning's advice for real runs (few batches, workers)
        fit(cfg)
    (work / "run" / "checkpoints" / "last.ckpt").replace(path)
    # the run's folders as fit would have stored them had the run been in path's folder, then ``stored``
    moved = {
        "out_dir": str(path.parent),
        "checkpoint_dir": str(path.parent),
        "export": {"dir": str(path.parent / "export")},
    }
    checkpoint = torch.load(path, weights_only=True)
    checkpoint["hyper_parameters"]["cfg"].update({**moved, **(stored or {})})
    torch.save(checkpoint, path)
    return path


#: model settings of the tiny students where ``tiny_model`` says nothing (FastFlow3D's own: ZeroFlow's network)
TINY_DEFAULTS = {"norm": "batch", "decoder": "linear", "correlation_levels": []}


def rows_of(pair, keep0, keep1):
    """``pair`` cut to the rows ``keep0`` of pc0 (and its per-point arrays) and ``keep1`` of pc1."""
    per0 = ("pc0", "ground0", "time0", "flow", "flow_valid", "classes", "instance", "dynamic")
    per1 = ("pc1", "ground1", "time1")
    changes = {name: getattr(pair, name)[keep0] for name in per0 if getattr(pair, name) is not None}
    changes.update({name: getattr(pair, name)[keep1] for name in per1 if getattr(pair, name) is not None})
    return dataclasses.replace(pair, **changes)
