"""Training data for the student: pseudo-flow shards (``label.py`` output) as torch samples and flat batches.

One sample (``StudentDataset[i]``) holds torch tensors:

- ``pc0`` (N0, 3) float32, ego frame of t (as stored); ``pc0_compensated`` (N0, 3): the same points moved into the
  ego frame of t + dt (``fastflow3d.model.compensate``), the network's input; ``pc1`` (N1, 3) float32, ego frame of
  t + dt; ``ego1_from_ego0`` (4, 4) float64; ``dt`` float64 seconds; ``ground0`` (N0,) / ``ground1`` (N1,) bool (the
  shards' masks; with ``data.remove_ground`` the network sees only the other points, see ``fastflow3d.module``);
- ``pseudo`` (N0, 3) float32: the teacher's RESIDUAL (ego-compensated) flow, the distillation target;
  ``confidence`` (N0,) float32; ``cluster`` (N0,) int32 (teacher cluster id, -1 = none);
- when the shard has ground truth: ``gt`` (N0, 3) float32 RESIDUAL flow, ``gt_valid`` (N0,) bool, ``gt_classes``
  (N0,) int32 (0 = background);
- ``sample_id`` str.

:func:`collate` concatenates samples into one flat batch (the model's input layout, see ``fastflow3d.voxelize``):
per-point tensors are concatenated (P0 rows, or P1 for ``pc1`` and ``ground1``), ``batch0`` / ``batch1`` (P0,) /
(P1,) int64 give each point's sample, ``ego1_from_ego0`` is (B, 4, 4), ``dt`` (B,), ``sample_id`` a list and
``batch_size`` an int.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import lightning as L
import numpy as np
import torch
import yaml
from torch.utils.data import DataLoader, Dataset

from fastflow3d.augment import Augmentation
from fastflow3d.model import compensate
from icpflow.geometry import full_to_residual
from icpflow.preprocess import Preprocessing
from icpflow.shards.reader import ShardDataset

GT_KEYS = ("gt", "gt_valid", "gt_classes")
PER_POINT0 = ("pc0", "pc0_compensated", "ground0", "pseudo", "confidence", "cluster", *GT_KEYS)
PER_POINT1 = ("pc1", "ground1")


class DataError(ValueError):
    """Training data cannot be used (missing or empty shard directory). The message is one line."""


class StudentDataset(Dataset):
    """The samples of one shard directory (a ``label.py`` out_dir) as torch tensors (module docstring); with
    ``augment`` (training only) each read is a fresh random augmentation (``fastflow3d.augment``) drawn from torch's
    random state (seeded per DataLoader worker by Lightning's ``seed_everything(workers=True)``)."""

    def __init__(self, shard_dir, augment: Augmentation | None = None):
        self.root = Path(shard_dir)
        self.augment = augment
        if not self.root.is_dir():
            raise DataError(f"{self.root}: shard directory does not exist")
        try:
            self.shards = ShardDataset(self.root)
        except FileNotFoundError:
            raise DataError(f"{self.root}: no index.json, not a finished label.py output") from None
        if len(self.shards) == 0:
            raise DataError(f"{self.root}: the shards hold no samples")

    def __len__(self) -> int:
        return len(self.shards)

    def __getitem__(self, index: int) -> dict:
        raw = self.shards[index]
        if self.augment is not None:
            raw = self.augment(raw, np.random.default_rng(int(torch.randint(0, 2**62, (1,)).item())))
        pc0, ego = raw["pc0"], raw["ego1_from_ego0"]
        sample = {
            "pc0": torch.from_numpy(pc0),
            "pc0_compensated": torch.from_numpy(compensate(pc0, ego)),
            "pc1": torch.from_numpy(raw["pc1"]),
            "ego1_from_ego0": torch.from_numpy(ego),
            "dt": torch.tensor(raw["dt"], dtype=torch.float64),
            "ground0": torch.from_numpy(raw["ground0"]),
            "ground1": torch.from_numpy(raw["ground1"]),
            "pseudo": torch.from_numpy(full_to_residual(raw["flow"], pc0, ego)),
            "confidence": torch.from_numpy(raw["confidence"]),
            "cluster": torch.from_numpy(raw["cluster"]),
            "sample_id": raw["sample_id"],
        }
        if "gt_flow" in raw:
            valid = raw.get("gt_flow_valid", np.ones(len(pc0), bool))
            classes = raw.get("gt_classes", np.zeros(len(pc0), np.int32))
            sample.update(
                gt=torch.from_numpy(full_to_residual(raw["gt_flow"], pc0, ego)),
                gt_valid=torch.from_numpy(valid),
                gt_classes=torch.from_numpy(classes),
            )
        return sample


def collate(samples: list[dict]) -> dict:
    """Flat batch of samples (module docstring); ground truth is kept only if every sample has it."""
    has_gt = all("gt" in s for s in samples)
    keys = [k for k in PER_POINT0 if has_gt or k not in GT_KEYS]
    batch = {key: torch.cat([s[key] for s in samples]) for key in (*keys, *PER_POINT1)}
    for name, cloud in (("batch0", "pc0"), ("batch1", "pc1")):
        batch[name] = torch.cat([torch.full((len(s[cloud]),), i, dtype=torch.int64) for i, s in enumerate(samples)])
    batch["ego1_from_ego0"] = torch.stack([s["ego1_from_ego0"] for s in samples])
    batch["dt"] = torch.stack([s["dt"] for s in samples])
    batch["sample_id"] = [s["sample_id"] for s in samples]
    batch["batch_size"] = len(samples)
    return batch


def split_samples(batch: dict, key: str = "batch0") -> list[slice]:
    """Slices of each sample's points in a collated batch (points of a sample are contiguous)."""
    counts = torch.bincount(batch[key].cpu(), minlength=batch["batch_size"]).tolist()
    ends = np.cumsum(counts).tolist()
    return [slice(end - count, end) for count, end in zip(counts, ends)]


def labeller_preprocessing(shard_dir) -> Preprocessing | None:
    """The preprocessing (height frame, ground and ego-motion settings, ``icpflow.preprocess``) of the teacher that
    labelled ``shard_dir``: the ``preprocessing`` block of its first shard's ``config`` attribute (``label.py``'s
    labeller config) or, for shards of older versions, the block that its ``teacher`` fields give; None when the
    shard has neither."""
    shards = StudentDataset(shard_dir).shards
    with h5py.File(shards.root / shards.entries[0][0], "r") as handle:
        text = handle.attrs.get("config")
    content = yaml.safe_load(text) if isinstance(text, str) else None
    content = content if isinstance(content, dict) else {}
    block = content.get("preprocessing", content.get("teacher"))
    return Preprocessing.from_dict(block) if isinstance(block, dict) else None


class ShardDataModule(L.LightningDataModule):
    """Train / val shard directories -> DataLoaders of flat batches (``workers`` loader processes per loader);
    ``augment`` (``Augmentation`` fields, or None) applies to the training samples only."""

    def __init__(self, train, val, batch_size: int = 8, workers: int = 0, augment: dict | None = None):
        super().__init__()
        self.train_dir, self.val_dir = train, val
        self.batch_size, self.workers = int(batch_size), int(workers)
        self.augment = Augmentation(**augment) if augment else None
        self.train_set = self.val_set = None

    def setup(self, stage: str | None = None) -> None:
        if stage in (None, "fit") and self.train_set is None:
            self.train_set = StudentDataset(self.train_dir, self.augment)
        if stage in (None, "fit", "validate") and self.val_set is None:
            self.val_set = StudentDataset(self.val_dir)

    def _loader(self, dataset, shuffle: bool) -> DataLoader:
        return DataLoader(
            dataset,
            batch_size=self.batch_size,
            shuffle=shuffle,
            num_workers=self.workers,
            collate_fn=collate,
            persistent_workers=self.workers > 0,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.train_set, shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.val_set, shuffle=False)
