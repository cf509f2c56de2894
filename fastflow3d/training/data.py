"""Training data for the student: pseudo-flow shards (``label.py`` output) as torch samples and flat batches.

One sample (``StudentDataset[i]``) holds torch tensors:

- ``pc0`` (N0, 3) float32, ego frame of t (as stored); ``pc0_compensated`` (N0, 3): the same points moved into the
  ego frame of t + dt (``fastflow3d.network.model.compensate``), the network's input; ``pc1`` (N1, 3) float32, ego frame
  of t + dt; ``ego1_from_ego0`` (4, 4) float64; ``dt`` float64 seconds; ``ground0`` (N0,) / ``ground1`` (N1,) bool (the
  shards' masks; with ``data.remove_ground`` the network sees only the other points, see
  ``fastflow3d.training.student_module``);
- ``pseudo`` (N0, 3) float32: the teacher's RESIDUAL (ego-compensated) flow, the distillation target;
  ``confidence`` (N0,) float32; ``cluster`` (N0,) int32 (teacher cluster id, -1 = none);
- when the shard has ground truth: ``gt`` (N0, 3) float32 RESIDUAL flow, ``gt_valid`` (N0,) bool, ``gt_classes``
  (N0,) int32 (0 = background);
- ``sample_id`` str.

:func:`collate` concatenates samples into one flat batch (the model's input layout, see
``fastflow3d.network.voxelize``): per-point tensors are concatenated (P0 rows, or P1 for ``pc1`` and ``ground1``),
``batch0`` / ``batch1`` (P0,) / (P1,) int64 give each point's sample, ``ego1_from_ego0`` is (B, 4, 4), ``dt`` (B,),
``sample_id`` a list and ``batch_size`` an int.

Training samples are cropped to what the network sees (``NetworkCrop``, in the DataLoader workers): the pc0 / pc1
rows of the input contract (``fastflow3d.network.contract``: inside the grid and, with ground removal, off the
ground); the batch then says
``network_points=True`` and the module runs the network on it as it is. The loss is the same as on the whole
scans (points outside the grid or on the ground never count), and the main process neither copies nor masks them.
``NetworkCrop.max_points`` (``data.train_points``) then keeps at most that many random points per scan: an inexact
speed-up (fewer points per pillar mean), off by default.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import lightning as L
import numpy as np
import torch
import yaml
from lightning.fabric.utilities.seed import pl_worker_init_function
from threadpoolctl import threadpool_limits
from torch.utils.data import DataLoader, Dataset, DistributedSampler

from fastflow3d.network.contract import ContractError, InputContract, upgrade
from fastflow3d.network.model import compensate
from fastflow3d.network.voxelize import Grid
from fastflow3d.training.augment import Augmentation
from icpflow.core.errors_and_signals import one_line
from icpflow.core.geometry import full_to_residual
from icpflow.shards.access import open_shard
from icpflow.shards.reader import ShardDataset

GT_KEYS = ("gt", "gt_valid", "gt_classes")
PER_POINT0 = ("pc0", "pc0_compensated", "ground0", "pseudo", "confidence", "cluster", *GT_KEYS)
PER_POINT1 = ("pc1", "ground1")


class DataError(ValueError):
    """Training data cannot be used (missing or empty shard directory). The message is one line."""


@dataclass(frozen=True)
class NetworkCrop:
    """The rows of a sample the network sees in training: those of the input ``contract``
    (``fastflow3d.network.contract.InputContract.network_mask``: inside the grid and, with ground removal, off the
    ground); then at most ``max_points`` random rows per scan (None = all)."""

    contract: InputContract
    max_points: int | None = None

    def __post_init__(self):
        if self.max_points is not None and self.max_points < 1:
            raise ValueError(f"data.train_points must be null or >= 1, got {self.max_points}")

    def rows(self, points: torch.Tensor, ground: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
        """Sorted row indices (K,) int64 of one scan's kept points (N, 3) with ground mask (N,); ``rng`` draws the
        ``max_points``."""
        rows = torch.nonzero(self.contract.network_mask(points, ground))[:, 0]
        if self.max_points is not None and len(rows) > self.max_points:
            rows = rows[torch.from_numpy(rng.permutation(len(rows))[: self.max_points])].sort().values
        return rows

    def __call__(self, sample: dict, rng: np.random.Generator) -> dict:
        """``sample`` (``StudentDataset`` layout) with the per-point tensors of both scans cut to the kept rows."""
        out = dict(sample, network_points=True)
        for keys, points, ground in ((PER_POINT0, "pc0_compensated", "ground0"), (PER_POINT1, "pc1", "ground1")):
            rows = self.rows(sample[points], sample[ground], rng)
            for key in keys:
                if key in sample:
                    out[key] = sample[key][rows]
        return out


class Draw(NamedTuple):
    """A training read: sample ``index`` with its random choices (augmentation, ``train_points``) drawn from
    ``entropy`` (the run's seed and the epoch) and the index alone, so they do not depend on which rank or DataLoader
    worker reads it."""

    index: int
    entropy: tuple[int, int]

    def rng(self) -> np.random.Generator:
        return np.random.default_rng([*self.entropy, self.index])


class StudentDataset(Dataset):
    """The samples of one shard directory (a ``label.py`` out_dir) as torch tensors (module docstring); with ``augment``
    (training only) each read is a random augmentation (``fastflow3d.training.augment``); with ``crop`` (training only)
    each sample is then cut to the network's points. The random choices of ``dataset[Draw(i, (seed, epoch))]`` (what
    :class:`EpochOrder` hands the DataLoader) are those of ``Draw.rng``; a plain ``dataset[i]`` draws fresh ones from
    torch's random state."""

    def __init__(self, shard_dir, augment: Augmentation | None = None, crop: NetworkCrop | None = None):
        self.root = Path(shard_dir)
        self.augment = augment
        self.crop = crop
        if not self.root.is_dir():
            what = "is a file, not a shard directory" if self.root.exists() else "shard directory does not exist"
            raise DataError(f"{self.root}: {what}")
        try:
            self.shards = ShardDataset(self.root)
        except FileNotFoundError:
            raise DataError(f"{self.root}: no index.json, not a finished label.py output") from None
        if len(self.shards) == 0:
            raise DataError(f"{self.root}: the shards hold no samples")

    def __len__(self) -> int:
        return len(self.shards)

    def __getitem__(self, index: int | Draw) -> dict:
        if isinstance(index, Draw):
            index, rng = index.index, index.rng()
        elif self.augment is not None or self.crop is not None:  # random choices to draw: fresh ones
            rng = np.random.default_rng(int(torch.randint(0, 2**62, (1,)).item()))
        else:
            rng = None
        raw = self.shards[index]
        if self.augment is not None:
            raw = self.augment(raw, rng)
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
        return sample if self.crop is None else self.crop(sample, rng)


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
    batch["network_points"] = all(s.get("network_points", False) for s in samples)
    return batch


def init_worker(worker_id: int, blas_threads: int, rank: int) -> None:
    """DataLoader ``worker_init_fn``: at most ``blas_threads`` BLAS threads in the worker (numpy's OpenBLAS would
    otherwise start one per core and take the trainer's cores); then Lightning's per-worker seeding, which Lightning
    adds itself only to loaders without a ``worker_init_fn``."""
    threadpool_limits(limits=blas_threads, user_api="blas")
    if os.environ.get("PL_SEED_WORKERS") == "1":
        pl_worker_init_function(worker_id, rank)


def split_samples(batch: dict, key: str = "batch0") -> list[slice]:
    """Slices of each sample's points in a collated batch (points of a sample are contiguous)."""
    counts = torch.bincount(batch[key].cpu(), minlength=batch["batch_size"]).tolist()
    ends = np.cumsum(counts).tolist()
    return [slice(end - count, end) for count, end in zip(counts, ends)]


def labeller_contract(shard_dir, remove_ground: bool, grid: Grid) -> InputContract:
    """The input contract of a student trained on ``shard_dir`` with ``remove_ground`` on ``grid``: the teacher's
    part (height frame, ground and ego-motion settings) from the labeller config of its first shard (``label.py``'s
    YAML: its ``preprocessing`` block, or the ``teacher`` fields of older versions), read by
    ``fastflow3d.network.contract.upgrade``. Shards whose labeller config holds neither are refused (DataError): nothing
    would say the height frame the student learns in."""
    shards = StudentDataset(shard_dir).shards
    first = shards.root / shards.entries[0][0]
    with open_shard(first) as handle:
        text = handle.attrs.get("config")
    try:
        content = yaml.safe_load(text) if isinstance(text, str) else None
    except yaml.YAMLError as error:  # e.g. a python/object tag: safe_load refuses it, never runs it
        problem = one_line(error)[:160]
        raise DataError(f"{first}: its labeller config is not plain YAML ({type(error).__name__}: {problem})") from None
    content = content if isinstance(content, dict) else {}
    if not isinstance(content.get("preprocessing", content.get("teacher")), dict):
        raise DataError(
            f"{first}: its labeller config holds no teacher settings (height frame, ground): not written by "
            "label.py? label the data with label.py"
        )
    try:
        return upgrade(content, remove_ground=remove_ground, grid=grid)
    except ContractError as error:
        raise DataError(f"{first}: its labeller config: {one_line(error)}") from None


class EpochOrder(DistributedSampler):
    """The training order: each epoch a permutation of the samples drawn from ``seed`` and the epoch number only,
    dealt round-robin to the ``world`` ranks (rank r gets positions r, r + world, ...). So a batch of b samples on
    each of w ranks holds the same samples as a batch of w x b on one process, whatever the split. When the
    samples do not divide among the ranks, the permutation's last ``len % world`` are left out of that epoch (other
    ones each epoch): no rank repeats a sample to fill its share (torch's DistributedSampler with
    ``drop_last=True``). Each index comes as a :class:`Draw`: its random choices depend on the seed, the epoch and
    the sample only.

    ``resume=(epoch, batches, batch_size)``: in that epoch, this rank's first ``batches`` batches were trained before
    a checkpoint (``ShardDataModule.state_dict``); its iteration starts after them, so a resumed run sees the samples
    an uninterrupted one would. ``len`` stays the whole share (Lightning counts the epoch's batches from it and
    continues its batch index from the checkpoint's)."""

    def __init__(self, dataset, world: int, rank: int, seed: int, resume: tuple[int, int, int] | None = None):
        super().__init__(dataset, num_replicas=world, rank=rank, shuffle=True, seed=seed, drop_last=True)
        self.resume = resume

    def __iter__(self):
        order = list(super().__iter__())
        if self.resume is not None:
            epoch, batches, batch_size = self.resume
            if epoch == self.epoch and batches * batch_size < len(order):
                order = order[batches * batch_size :]
        return iter([Draw(index, (self.seed, self.epoch)) for index in order])


class ShardDataModule(L.LightningDataModule):
    """Train / val shard directories -> DataLoaders of flat batches (``workers`` loader processes per loader, each
    with ``worker_blas_threads`` BLAS threads); ``augment`` (``Augmentation`` fields, or None) and ``crop``
    (``NetworkCrop``, or None) apply to the training samples only. The training order is :class:`EpochOrder`'s
    (``seed``), on one process or several; its position is saved in checkpoints (``state_dict``) and a resume
    continues it."""

    def __init__(
        self,
        train,
        val,
        batch_size: int = 8,
        workers: int = 0,
        augment: dict | None = None,
        crop: NetworkCrop | None = None,
        worker_blas_threads: int = 1,
        seed: int = 0,
    ):
        super().__init__()
        self.train_dir, self.val_dir = train, val
        self.batch_size, self.workers = int(batch_size), int(workers)
        self.augment = Augmentation(**augment) if augment else None
        self.crop = crop
        self.worker_blas_threads = int(worker_blas_threads)
        self.seed = int(seed)
        self.train_set = self.val_set = None
        self.resume: tuple[int, int] | None = None  # (epoch, batches trained in it) of the checkpoint resumed

    @classmethod
    def from_config(cls, data: dict, contract: InputContract, seed: int = 0) -> ShardDataModule:
        """The data module of a training config's ``data`` block (plain dict, ``conf/data/shards.yaml``) for a
        student with input ``contract``: training samples cropped to the network's points (``train_points``), in the
        order of ``seed``."""
        crop = NetworkCrop(contract, data.get("train_points"))
        return cls(
            data["train"],
            data["val"],
            data["batch_size"],
            data["workers"],
            data["augment"],
            crop,
            data.get("worker_blas_threads", 1),
            seed,
        )

    def setup(self, stage: str | None = None) -> None:
        if stage in (None, "fit") and self.train_set is None:
            self.train_set = StudentDataset(self.train_dir, self.augment, self.crop)
        if stage in (None, "fit", "validate") and self.val_set is None:
            self.val_set = StudentDataset(self.val_dir)

    def _loader(self, dataset, shuffle: bool, sampler=None) -> DataLoader:
        return DataLoader(
            dataset,
            batch_size=self.batch_size,
            shuffle=shuffle,
            sampler=sampler,
            num_workers=self.workers,
            collate_fn=collate,
            persistent_workers=self.workers > 0,
            worker_init_fn=functools.partial(
                init_worker, blas_threads=self.worker_blas_threads, rank=self.trainer.global_rank if self.trainer else 0
            ),
        )

    def _world(self) -> tuple[int, int]:
        """(processes, this one's rank) of the trainer (1, 0 without one)."""
        return (self.trainer.world_size, self.trainer.global_rank) if self.trainer is not None else (1, 0)

    def train_dataloader(self) -> DataLoader:
        world, rank = self._world()
        resume = (*self.resume, self.batch_size) if self.resume else None
        sampler = EpochOrder(self.train_set, world, rank, self.seed, resume)
        return self._loader(self.train_set, shuffle=False, sampler=sampler)

    def state_dict(self) -> dict:
        """Saved in checkpoints: the epoch and the batches of it each rank has trained (Lightning's progress)."""
        if self.trainer is None:
            return {}
        trained = self.trainer.fit_loop.epoch_loop.batch_progress.current.processed
        return {"epoch": int(self.trainer.current_epoch), "batches": int(trained)}

    def load_state_dict(self, state: dict) -> None:
        """Before a resume's loaders are built: where the training order stopped (checkpoints of older versions
        hold nothing: the epoch then starts at its first batch)."""
        if "epoch" in state and "batches" in state:
            self.resume = (int(state["epoch"]), int(state["batches"]))

    def val_dataloader(self) -> DataLoader:
        """The validation samples; with several processes, each rank gets its share of them once, none repeated
        (Lightning's own sampler would pad the shares with repeats to equal length, which the val metrics, summed
        over ranks in ``StudentModule.on_validation_epoch_end``, would count twice)."""
        world, rank = self._world()
        if world <= 1:
            return self._loader(self.val_set, shuffle=False)
        from lightning.pytorch.overrides.distributed import UnrepeatedDistributedSampler

        sampler = UnrepeatedDistributedSampler(self.val_set, num_replicas=world, rank=rank, shuffle=False)
        return self._loader(self.val_set, shuffle=False, sampler=sampler)
