"""The student's LightningModule: FastFlow3D trained on pseudo-labels (or ground truth), validated with the paper's
metrics.

Its arguments (:class:`StudentModule`) come from ``conf/train.yaml``'s ``module`` node: the network, the loss
(``name``: ``distillation`` on the teacher's pseudo-labels, or ``supervised`` on ground truth with
``background_weight``; ``weighting`` and ``bucket_edges``, see ``fastflow3d.training.loss``), the optimiser and schedule
(Hydra ``_partial_`` targets, ``conf/optim``, ``conf/scheduler``; counted in optimiser steps), ``metrics``
(``crop``, ``bev_every``), the input contract (``fastflow3d.network.contract``) and ``out_dir``.

The network sees the rows of the input contract: with ground removal (ZeroFlow's setting) only the non-ground points
of pc0 and pc1 (the shards' ``ground0`` / ``ground1``) inside the grid; other pc0 points get residual 0 (full flow =
ego flow) and are left out of the loss.

Validation scores the full flow of every pc0 point (network residual + ego flow; pc0 points outside the grid or, with
ground removal, on the ground get the ego flow) with ``icpflow.evaluation.metrics.frame_pair_stats`` (ground excluded
there): against the shards' ground truth when they carry it, else against the pseudo-labels with "foreground" = points
the teacher clustered (``val/against_gt`` is 1 or 0, and the TensorBoard text ``val/against`` says ``gt`` or
``pseudo``). Logged: ``train/loss``, ``val/loss``, ``val/<category>/<column>``
(point-weighted, categories dynamic_fg, static_fg, static_bg, overall; columns EPE, AccS, AccR, Outliers) and a BEV
image every ``bev_every`` validations (also written to ``<out_dir>/bev/``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

import lightning as L
import numpy as np
import torch

import icpflow
from fastflow3d.network.contract import InputContract
from fastflow3d.network.model import FastFlow3D
from fastflow3d.training.data import split_samples
from fastflow3d.training.loss import flow_loss, object_loss
from icpflow.core.frame_pair import FramePair
from icpflow.core.geometry import residual_to_full
from icpflow.evaluation import metrics as metrics_module

LOSSES = ("distillation", "supervised")


log = logging.getLogger(__package__)  # the training room's logger: its console lines read "training: ..."


class NonFiniteLoss(RuntimeError):
    """The training loss became NaN or Inf; the message (one line) names the step and the batch's sample ids."""


class StudentModule(L.LightningModule):
    """FastFlow3D as ``self.model``, trained as its explicit arguments say; instantiated from ``conf/train.yaml``'s
    ``module`` node (``fastflow3d.training.trainer.build_module``), as in lightning-hydra-template.

    ``model``: the network (``fastflow3d.artifact.checkpoint.build_student`` of ``conf/model``); ``loss``: ``name``,
    ``weighting``, ``bucket_edges``, ``background_weight``, ``object_weight`` (``fastflow3d.training.loss``);
    ``optimiser``: ``optimiser(params)`` and ``scheduler``: ``scheduler(optimiser, total_steps=...)``, Hydra
    ``_partial_`` targets (``conf/optim``,
    ``conf/scheduler``); ``contract``: the input contract (``fastflow3d.network.contract``); ``metrics``: ``crop`` and
    ``bev_every``; ``out_dir``: where BEV images go (``<out_dir>/bev``). ``fastflow3d.training.trainer.build_module``
    also saves the whole resolved training config as ``hparams.cfg`` (export, evaluation and resume need only a
    checkpoint); it is never read here."""

    def __init__(
        self,
        model: FastFlow3D,
        loss: dict,
        optimiser: Callable,
        scheduler: Callable,
        contract: InputContract,
        metrics: dict,
        out_dir: str,
    ):
        super().__init__()
        self.loss_options = dict(loss)
        if self.loss_options["name"] not in LOSSES:
            raise ValueError(f"loss.name must be one of {', '.join(LOSSES)}, got {self.loss_options['name']!r}")
        self.model, self.contract = model, contract
        self.make_optimiser, self.make_schedule = optimiser, scheduler
        self.metric_options, self.out_dir = dict(metrics), Path(out_dir)
        self.validations = 0
        self.scores = metrics_module.MetricAccumulator()
        self.against = None

    def forward(self, batch: dict):
        """(residual (P0, 3), valid (P0,)) of a collated batch; valid = the network predicted the point (its rows in
        the input contract: inside the grid and, with ground removal, not ground); residual is 0 elsewhere. A batch
        already cut to those rows (``network_points``, ``fastflow3d.training.data.NetworkCrop``) goes to the network as
        it is."""
        if batch.get("network_points"):
            return self.model(
                batch["pc0_compensated"], batch["batch0"], batch["pc1"], batch["batch1"], batch["batch_size"]
            )
        keep0 = self.contract.network_mask(batch["pc0_compensated"], batch["ground0"])
        keep1 = self.contract.network_mask(batch["pc1"], batch["ground1"])
        kept, kept_valid = self.model(
            batch["pc0_compensated"][keep0],
            batch["batch0"][keep0],
            batch["pc1"][keep1],
            batch["batch1"][keep1],
            batch["batch_size"],
        )
        residual = kept.new_zeros(len(keep0), 3).index_put((keep0,), kept)
        valid = torch.zeros_like(keep0).index_put((keep0,), kept_valid)
        return residual, valid

    def loss(self, pred: torch.Tensor, valid: torch.Tensor, batch: dict) -> torch.Tensor:
        """The configured loss of residual predictions (P0, 3) on the points the network predicted (``valid``):
        against the pseudo-labels (``distillation``) or the ground truth (``supervised``, background points
        weighted by ``background_weight``), weighted as ``loss.weighting`` says, plus ``object_weight`` times the
        object term on the teacher's clusters (``fastflow3d.training.loss``)."""
        options, size = self.loss_options, batch["batch_size"]
        dt = batch["dt"].float()[batch["batch0"]]  # speeds in float32, also under bf16 autocast
        weighting = {"weighting": options["weighting"], "dt": dt, "bucket_edges": options["bucket_edges"]}
        if options["name"] == "supervised":
            if "gt" not in batch:
                raise ValueError(f"loss.name=supervised needs ground truth, but samples {batch['sample_id']} have none")
            background = torch.full_like(pred[:, 0], float(options["background_weight"]))
            weight = torch.where(batch["gt_classes"] > 0, torch.ones_like(background), background)
            target, valid = batch["gt"], valid & batch["gt_valid"]
            loss = flow_loss(pred, target, batch["batch0"], valid, size, **weighting, point_weight=weight)
        else:
            target = batch["pseudo"]
            loss = flow_loss(pred, target, batch["batch0"], valid, size, **weighting)
        if options.get("object_weight", 0.0) > 0:  # older checkpoints' configs have no object_weight
            loss = loss + options["object_weight"] * object_loss(
                pred, target, batch["cluster"], batch["batch0"], valid, size
            )
        return loss

    def training_step(self, batch: dict, batch_index: int) -> torch.Tensor:
        pred, valid = self(batch)
        if int(valid.sum()) < 2:  # the network normalised them with its running statistics (model.PillarEmbedder)
            log.warning(
                "step %d: samples %s hold %d point(s) of pc0 in the network's grid: too few for batch statistics; "
                "trained on with the running ones (check these samples)",
                self.global_step,
                ", ".join(map(str, batch["sample_id"])),
                int(valid.sum()),
            )
        loss = self.loss(pred, valid, batch)
        if not torch.isfinite(loss):  # stop at once: a NaN step poisons the weights and every checkpoint after it
            raise NonFiniteLoss(
                f"non-finite training loss ({loss.item()}) at step {self.global_step} on samples "
                f"{', '.join(map(str, batch['sample_id']))}; no checkpoint is written from it"
            )
        self.log("train/loss", loss, batch_size=batch["batch_size"], prog_bar=True)
        return loss

    # ------------------------------------------------------------------------------------------------ validation

    def on_validation_epoch_start(self) -> None:
        self.scores = metrics_module.MetricAccumulator()
        self.against = None

    def validation_step(self, batch: dict, batch_index: int) -> None:
        pred, valid = self(batch)
        self.log("val/loss", self.loss(pred, valid, batch), batch_size=batch["batch_size"], sync_dist=True)
        against = "gt" if "gt" in batch else "pseudo"
        if self.against not in (None, against):
            raise ValueError(f"validation shards mix samples with and without ground truth ({batch['sample_id']})")
        self.against = against
        residual = pred.detach().float().cpu().numpy()
        host = {key: value.cpu().numpy() for key, value in batch.items() if torch.is_tensor(value)}
        pairs = zip(split_samples(batch, "batch0"), split_samples(batch, "batch1"), batch["sample_id"])
        for b, (rows0, rows1, sample_id) in enumerate(pairs):
            pair = self._pair(host, b, rows0, rows1, sample_id)
            predicted = residual_to_full(residual[rows0], pair.pc0, pair.ego1_from_ego0)
            self.scores.add(metrics_module.frame_pair_stats(pair, predicted, crop=self.metric_options["crop"]))
            if batch_index == 0 and b == 0 and self._draw_now():
                self._draw(pair, predicted)

    def _pair(self, host: dict, b: int, rows0: slice, rows1: slice, sample_id: str) -> FramePair:
        """Sample b of a batch (numpy arrays) as a FramePair whose ``flow`` is the reference (gt or pseudo)."""
        pc0, ego = host["pc0"][rows0], host["ego1_from_ego0"][b]
        if self.against == "gt":
            reference, classes, flow_valid = host["gt"][rows0], host["gt_classes"][rows0], host["gt_valid"][rows0]
        else:
            reference, flow_valid = host["pseudo"][rows0], None
            classes = (host["cluster"][rows0] >= 0).astype(np.int32)
        return FramePair(
            pc0,
            host["pc1"][rows1],
            ego1_from_ego0=ego,
            ground0=host["ground0"][rows0],
            flow=residual_to_full(reference, pc0, ego),
            flow_valid=flow_valid,
            classes=classes,
            dt=float(host["dt"][b]),
            sample_id=sample_id,
        )

    def _draw_now(self) -> bool:
        every = int(self.metric_options["bev_every"])
        return (
            every > 0 and not self.trainer.sanity_checking and self.validations % every == 0 and self.global_rank == 0
        )

    def _draw(self, pair: FramePair, predicted: np.ndarray) -> None:
        """BEV image of the first validation sample: PNG under out_dir/bev and, with TensorBoard, an image."""
        from icpflow.viz.pictures import plot_bev

        path = self.out_dir / "bev" / f"val_step{self.global_step:07d}.png"
        plot_bev(pair, path, predicted, title=f"student at step {self.global_step} vs {self.against}")
        experiment = getattr(self.logger, "experiment", None)
        if hasattr(experiment, "add_image"):
            import matplotlib.image

            image = matplotlib.image.imread(path)[..., :3]
            experiment.add_image("val/bev", image, self.global_step, dataformats="HWC")

    def on_validation_epoch_end(self) -> None:
        sums = torch.tensor(np.stack([self.scores.sums[c] for c in metrics_module.CATEGORIES]), device=self.device)
        sums = self.trainer.strategy.reduce(sums, reduce_op="sum")
        self.scores.sums = dict(zip(metrics_module.CATEGORIES, sums.cpu().double().numpy()))
        table = self.scores.table()["point_weighted"]
        for category in metrics_module.CATEGORIES:
            for column in metrics_module.COLUMNS:
                self.log(f"val/{category}/{column}", float(table[category][column]), sync_dist=True)
        self.log("val/against_gt", float(self.against == "gt"), sync_dist=True)
        experiment = getattr(self.logger, "experiment", None)
        if not self.trainer.sanity_checking:
            if self.validations == 0 and hasattr(experiment, "add_text"):
                experiment.add_text("val/against", self.against or "none", self.global_step)
            self.validations += 1

    # ------------------------------------------------------------------------------------------------ optimiser

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        """Every checkpoint records the package version that wrote it, as shards and exports do."""
        checkpoint["package_version"] = icpflow.__version__

    def configure_optimizers(self):
        """The optimiser and its schedule (``fastflow3d.training.schedules``) from the partials given, stepped every
        optimiser step."""
        optimiser = self.make_optimiser(self.parameters())
        schedule = self.make_schedule(optimiser, total_steps=int(self.trainer.estimated_stepping_batches))
        return {"optimizer": optimiser, "lr_scheduler": {"scheduler": schedule, "interval": "step"}}
