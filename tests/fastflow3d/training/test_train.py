"""Training stage: configs compose, flat batches, ground removal, fast_dev_run, a final validation, the export at
the end, TensorBoard logs, overfitting one pair, resume, checkpoint contract."""

import inspect
import json
import logging
import subprocess
import sys
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

import icpflow
from fastflow3d.artifact.checkpoint import CheckpointError, build_student, load_student
from fastflow3d.artifact.file_format import FILE_NAMES, INT8, INT8_FILE_NAME, METADATA_NAME
from fastflow3d.network.model import FastFlow3D
from fastflow3d.network.voxelize import Grid
from fastflow3d.training.data import DataError, StudentDataset, collate
from fastflow3d.training.run_folder import TrainError
from fastflow3d.training.trainer import accumulation, build_trainer, fit, settle_batch
from icpflow.core.geometry import ego_flow, transform_points
from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.scans.preprocess import Preprocessing
from icpflow.shards.writer import write_index

from helpers.data import REPO
from helpers.shards import TEACHER, write_pseudo_labels
from helpers.training import CONF, TINY, TINY_MODEL, student_module
from helpers.training import compose_train as _compose
from helpers.training import train_cfg as _cfg

GROUPS = ("data", "model", "trainer", "logger", "callbacks", "optim", "scheduler", "experiment")
XL_PARAMETERS = 110_618_147  # FastFlow3D XL (conf/model/fastflow3d_xl.yaml), any grid


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


# ---------------------------------------------------------------------------------------------------- configs


@pytest.mark.parametrize("group,option", [(g, o) for g in GROUPS for o in _options(g)])
def test_every_config_composes(group, option, tmp_path):
    cfg = _compose(f"{group}={option}", f"out_dir={tmp_path}")
    plain = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
    for key in ("train", "val", "batch_size", "workers"):
        assert key in plain["data"]
    assert "max_steps" in plain["trainer"] and "ckpt_path" in plain and plain["out_dir"] == str(tmp_path)
    trainer_args = set(inspect.signature(L.Trainer.__init__).parameters)
    assert set(plain["trainer"]) <= trainer_args, set(plain["trainer"]) - trainer_args
    model_args = set(inspect.signature(FastFlow3D.__init__).parameters)
    assert plain["model"]["_target_"] == "fastflow3d.network.model.FastFlow3D"
    assert set(plain["model"]) - {"_target_"} <= model_args
    callbacks = [instantiate(c) for c in cfg.callbacks.values()]
    assert any(
        isinstance(c, L.pytorch.callbacks.ModelCheckpoint) and c.monitor == "val/dynamic_fg/EPE" for c in callbacks
    )
    assert str(Path(cfg.checkpoint_dir).parent) == str(tmp_path)
    assert isinstance(instantiate(cfg.logger), L.pytorch.loggers.TensorBoardLogger)
    # optimiser and schedule are partials: optim(params), scheduler(optimiser, total_steps=...)
    weight = torch.nn.Parameter(torch.zeros(1))
    optimiser = instantiate(cfg.optim)(params=[weight])
    schedule = instantiate(cfg.scheduler)(optimiser, total_steps=50)
    base = instantiate(cfg.optim).keywords["lr"]
    seen = []
    for _ in range(50):
        optimiser.step()
        schedule.step()
        seen.append(optimiser.param_groups[0]["lr"])
    assert all(0 < lr <= base * (1 + 1e-9) for lr in seen), seen  # a schedule scales the lr down, never up


def test_model_configs_build_the_issue_networks():
    # the paper and zeroflow recipes train ZeroFlow's networks exactly (the CPU recipes add a cost volume)
    default = build_student(OmegaConf.to_container(_compose("experiment=paper").model))
    assert OmegaConf.to_container(_compose("experiment=zeroflow").model) == OmegaConf.to_container(
        _compose("experiment=paper").model
    )
    assert (default.grid.nx, default.grid.ny) == (512, 512)
    assert sum(p.numel() for p in default.parameters()) == 6_815_619
    xl = _compose("experiment=paper", "model=fastflow3d_xl").model
    assert xl.cell == 0.1 and xl.pillar_channels == 64 and len(xl.stage_channels) == 4
    assert Grid(tuple(xl.x_range), tuple(xl.y_range), tuple(xl.z_range), xl.cell).nx == 1024
    with pytest.raises(ValueError, match="_target_"):
        build_student({"_target_": "os.system", "cell": 1.0})


def test_xl_config_is_zeroflows_and_runs_forward_and_backward():
    """conf/model/fastflow3d_xl.yaml is ZeroFlow's FastFlow3D XL (kylevedder/zeroflow: FastFlowUNetXL and its AV2
    configs): 0.1 m pillars over +-51.2 m (1024 x 1024), 64 pillar channels, encoders of 128 / 256 / 512 / 1024
    channels with 3 / 5 / 5 / 5 extra convs, decoders (2048, 1024, 1024) ... (256, 128, 128), a 128-channel output and
    a head on 4 * 64 + 3 features. The network is built on a +-3.2 m crop (64 x 64; the weights do not depend on
    the grid) and runs one batch of two samples forward and backward."""
    xl = OmegaConf.to_container(_compose("experiment=paper", "model=fastflow3d_xl").model)
    assert xl["x_range"] == xl["y_range"] == [-51.2, 51.2] and xl["z_range"] == [-3.0, 3.0] and xl["cell"] == 0.1
    model = build_student({**xl, "x_range": [-3.2, 3.2], "y_range": [-3.2, 3.2]})
    assert model.embedder.linear.out_features == 64
    assert [[block[0].out_channels for block in stage] for stage in model.unet.encoder] == [
        [128] * 4,
        [256] * 6,
        [512] * 6,
        [1024] * 6,
    ]
    assert [
        (step.low.in_channels, step.low.out_channels, step.fuse[1].out_channels) for step in model.unet.decoder
    ] == [(2048, 1024, 1024), (1024, 512, 512), (512, 256, 256), (256, 128, 128)]
    assert model.unet.final.out_channels == 128 and model.head[0].in_features == 259
    assert sum(p.numel() for p in model.parameters()) == XL_PARAMETERS
    gen = torch.Generator().manual_seed(0)
    pc0, pc1 = (
        torch.rand(3000, 3, generator=gen) * torch.tensor([8.0, 8.0, 4.0]) - torch.tensor([4.0, 4.0, 2.0])
        for _ in range(2)
    )
    batch = (torch.arange(3000) >= 1500).long()
    residual, valid = model(pc0, batch, pc1, batch, 2)
    assert residual.shape == (3000, 3) and 0 < valid.sum() < 3000 and torch.all(residual[~valid] == 0)
    residual.square().sum().backward()
    grads = [p.grad for p in model.parameters()]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert model.unet.encoder[3][-1][0].weight.grad.abs().sum() > 0  # the deepest (1024-channel) stage learns


def test_experiment_recipes():
    """Rules the recipes keep (their numbers live only in conf/): the paper and zeroflow recipes train ZeroFlow's
    network exactly (test_model_configs_build_the_issue_networks), zeroflow's effective batch is 64 as in ZeroFlow,
    ``python train.py`` alone reads what ``python label.py`` alone writes, and a group given on the command line
    beats the experiment's."""
    zeroflow = _compose("experiment=zeroflow")
    assert zeroflow.effective_batch == 64  # whatever the devices (test_effective_batch_holds_for_any_split)
    quick = _compose()  # python train.py with no arguments
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        train_labels = compose("label").out_dir
        val_labels = compose("label", ["split=val"]).out_dir
    assert (quick.data.train, quick.data.val) == (train_labels, val_labels)
    assert quick.trainer.max_steps > 0 and quick.trainer.accelerator == "cpu"
    xl = _compose("experiment=paper", "model=fastflow3d_xl").model  # the xl grid, whatever the experiment
    assert _compose("model=fastflow3d_xl").model.cell == xl.cell != quick.model.cell


@pytest.mark.parametrize("batch, devices, nodes, accumulated", [(1, 8, 1, 8), (8, 4, 1, 2), (8, 2, 1, 4), (2, 4, 2, 4)])
def test_effective_batch_holds_for_any_split(batch, devices, nodes, accumulated):
    """Issue 34.3: effective_batch sets the accumulation, batch x accumulation x devices x nodes = 64 (1x8x8, 8x2x4,
    a CPU 2-process split, two nodes); a split that cannot reach it is one line."""
    assert accumulation(64, batch, devices, nodes) == accumulated
    assert batch * accumulated * devices * nodes == 64
    with pytest.raises(TrainError, match=r"^effective_batch=64 is not a multiple of .* = 5 x 2 x 1 = 10;"):
        accumulation(64, 5, 2, 1)


@pytest.mark.parametrize("split", ["cpu", "ddp_cpu"])
def test_the_trainer_of_a_run_reaches_the_recipes_effective_batch(split):
    """The zeroflow recipe's Trainer, on one CPU process or as 2 DDP processes (built, not run): its accumulation
    makes the effective batch 64, and the line the run prints says the split."""
    cfg = _compose("experiment=zeroflow", f"trainer={split}", "~logger", "~callbacks")
    trainer = build_trainer(cfg)
    effective, line = settle_batch(cfg, trainer)
    expected = {"cpu": (8, 1), "ddp_cpu": (4, 2)}[split]
    assert (trainer.accumulate_grad_batches, trainer.num_devices) == expected and effective == 64
    assert (
        line == f"effective batch 64 = 8 per device x {expected[0]} accumulated x {expected[1]} device(s) x 1 node(s)"
    )
    plain = _compose("trainer.accumulate_grad_batches=3", "data.batch_size=2", "~logger", "~callbacks")
    assert settle_batch(plain, build_trainer(plain))[0] == 6  # no effective_batch: as configured


# ---------------------------------------------------------------------------------------------------- tiny shards


@pytest.fixture(scope="module")
def pairs():
    dataset = SyntheticDataset(
        split="train", num_sequences=1, frames_per_sequence=3, beams=32, azimuth_resolution_deg=1.0
    )
    return [dataset.pair(i) for i in range(len(dataset))]


@pytest.fixture(scope="module")
def shards(pairs, tmp_path_factory):
    root = tmp_path_factory.mktemp("shards")
    return {
        "gt": write_pseudo_labels(root / "gt", pairs),
        "pseudo": write_pseudo_labels(root / "pseudo", pairs[:1], False),
        "one": write_pseudo_labels(root / "one", pairs[:1]),
    }


# ---------------------------------------------------------------------------------------------------- data


def test_collate_flat_batch(shards, pairs):
    dataset = StudentDataset(shards["gt"])
    batch = collate([dataset[0], dataset[1]])
    n0 = [len(p.pc0) for p in pairs[:2]]
    assert batch["batch_size"] == 2 and batch["sample_id"] == [p.sample_id for p in pairs[:2]]
    assert batch["batch0"].tolist() == [0] * n0[0] + [1] * n0[1]
    assert batch["pc1"].shape == (sum(len(p.pc1) for p in pairs[:2]), 3) and batch["ego1_from_ego0"].shape == (2, 4, 4)
    first = slice(0, n0[0])
    np.testing.assert_allclose(
        batch["pc0_compensated"][first].numpy(), transform_points(pairs[0].ego1_from_ego0, pairs[0].pc0), atol=1e-5
    )
    residual = pairs[0].flow - ego_flow(pairs[0].pc0, pairs[0].ego1_from_ego0)
    np.testing.assert_allclose(batch["pseudo"][first].numpy(), residual, atol=1e-5)
    np.testing.assert_allclose(batch["gt"][first].numpy(), residual, atol=1e-5)
    assert batch["gt_classes"].shape == (sum(n0),) and batch["pseudo"].dtype == torch.float32
    mixed = collate([dataset[0], StudentDataset(shards["pseudo"])[0]])
    assert "gt" not in mixed and mixed["pseudo"].shape == (n0[0] * 2, 3)


def test_loss_choice_and_per_sample_dt():
    cfg = OmegaConf.to_container(_compose(*TINY), resolve=True)
    pred = torch.zeros(4, 3)
    batch = {
        "pseudo": torch.tensor([[0.05, 0, 0], [0.0, 0, 0], [0.05, 0, 0], [0, 0.0, 0]]),
        "batch0": torch.tensor([0, 0, 1, 1]),
        "batch_size": 2,
        "dt": torch.tensor([0.1, 0.05], dtype=torch.float64),
        "confidence": torch.tensor([1.0, 1.0, 0.5, 0.0]),
        "gt": torch.tensor([[1.0, 0, 0]] * 4),
        "gt_classes": torch.tensor([1, 0, 0, 0], dtype=torch.int32),
        "gt_valid": torch.ones(4, dtype=torch.bool),
        "sample_id": ["a", "b"],
    }
    valid = torch.ones(4, dtype=torch.bool)

    def loss(**options):
        module = student_module({**cfg, "loss": {**cfg["loss"], **options}})
        return module.loss(pred, valid, batch).item()

    assert loss(weighting="uniform") == pytest.approx((0.025 + 0.025) / 2)
    # 0.05 m is 0.5 m/s at dt 0.1 s (weight 0.1) but 1 m/s at dt 0.05 s (weight 1)
    assert loss(weighting="speed") == pytest.approx((0.1 * 0.05 / 2 + 1.0 * 0.05 / 2) / 2)
    # buckets (0.4, 1.0 m/s): each sample has one static point (error 0) and one moving point (error 0.05)
    assert loss(weighting="buckets") == pytest.approx((0.05 + 0.05) / 2)
    # supervised: background weighs background_weight; all errors are 1
    assert loss(name="supervised", weighting="uniform", background_weight=0.1) == pytest.approx(
        ((1 + 0.1) / 2 + (0.1 + 0.1) / 2) / 2
    )
    with pytest.raises(TrainError, match="loss.name must be one of"):
        loss(name="chamfer")


def test_ground_removal_network_sees_non_ground_points_only(shards):
    cfg = OmegaConf.to_container(_compose(*TINY), resolve=True)
    assert cfg["data"]["remove_ground"]  # the default, as ZeroFlow
    dataset = StudentDataset(shards["gt"])
    batch = collate([dataset[0], dataset[1]])
    ground0, ground1 = batch["ground0"], batch["ground1"]
    assert 0 < ground0.sum() < len(ground0) and 0 < ground1.sum() < len(ground1)
    torch.manual_seed(0)
    module = student_module(cfg).eval()
    with torch.no_grad():
        residual, valid = module(batch)
        kept, kept_valid = module.model(
            batch["pc0_compensated"][~ground0],
            batch["batch0"][~ground0],
            batch["pc1"][~ground1],
            batch["batch1"][~ground1],
            2,
        )
    assert torch.equal(residual[~ground0], kept) and torch.equal(valid[~ground0], kept_valid) and kept_valid.any()
    assert not valid[ground0].any() and torch.all(residual[ground0] == 0)  # ground: full flow = ego flow
    # the loss ignores ground points: pseudo-labels on the ground do not change it
    moved = {**batch, "pseudo": torch.where(ground0[:, None], batch["pseudo"] + 5.0, batch["pseudo"])}
    assert module.loss(residual, valid, moved) == module.loss(residual, valid, batch)

    every = student_module({**cfg, "data": {**cfg["data"], "remove_ground": False}}).eval()
    every.model.load_state_dict(module.model.state_dict())
    with torch.no_grad():
        full, full_valid = every(batch)
    assert full_valid[ground0].any() and not torch.equal(full[~ground0], kept)  # the ground changes the pillars


def test_teacher_settings_saved_with_the_model(shards, pairs, tmp_path):
    """The input contract saved with the model takes the teacher's part from the shards (here shards of an older
    version: only the teacher's fields, the synthetic frame), ground removal and the grid from the run; shards
    without a labeller config are refused in one line (nothing would say the height frame)."""
    from fastflow3d.training.trainer import training_contract

    contract = training_contract(_cfg(tmp_path, shards["gt"], shards["gt"]))
    assert contract.preprocessing == Preprocessing.from_teacher(TEACHER)
    assert contract.preprocessing.frame.ground_z == 0.0 and contract.preprocessing.ground.sensor_height == 1.9
    assert contract.remove_ground and contract.grid.cell == 1.0
    bare = write_pseudo_labels(tmp_path / "bare", pairs[:1], config="test: true\n")
    with pytest.raises(TrainError, match=r"data.train: .*bare/shard_000000.h5: its labeller config holds no teacher"):
        fit(_cfg(tmp_path, bare, bare))


def test_missing_or_empty_shard_dir_is_one_line(tmp_path):
    with pytest.raises(DataError, match="does not exist"):
        StudentDataset(tmp_path / "nowhere")
    with pytest.raises(DataError, match="no index.json"):
        StudentDataset(tmp_path)
    (tmp_path / "empty").mkdir()
    write_index(tmp_path / "empty" / "index.json", {"config_hash": "x", "shards": []})
    with pytest.raises(DataError, match="no samples"):
        StudentDataset(tmp_path / "empty")
    expected = r"data.train: .*nowhere: shard directory does not exist; .*python label.py split=train"
    with pytest.raises(TrainError, match=expected):
        fit(_cfg(tmp_path, tmp_path / "nowhere", tmp_path / "nowhere"))


def test_train_script_says_how_to_label(tmp_path):
    result = subprocess.run(
        [sys.executable, str(REPO / "train.py"), f"data.train={tmp_path / 'none'}", f"out_dir={tmp_path / 'run'}"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.startswith("train:")]
    assert len(lines) == 1 and "python label.py split=train" in lines[0], result.stderr


# ---------------------------------------------------------------------------------------------------- training


def test_fast_dev_run_against_gt_and_pseudo(shards, tmp_path):
    trainer = fit(_cfg(tmp_path, shards["gt"], shards["gt"], "trainer.fast_dev_run=true", "data.batch_size=2"))
    assert trainer.state.finished and trainer.global_step == 1
    metrics = trainer.callback_metrics
    assert metrics["val/against_gt"] == 1.0 and np.isfinite(metrics["val/dynamic_fg/EPE"].item())
    assert {"val/static_fg/EPE", "val/static_bg/EPE", "val/dynamic_fg/AccS", "val/dynamic_fg/AccR"} <= set(metrics)
    trainer = fit(
        _cfg(
            tmp_path,
            shards["gt"],
            shards["pseudo"],
            "trainer.fast_dev_run=true",
            "loss.weighting=speed",
            "data.remove_ground=false",
        )
    )
    assert trainer.callback_metrics["val/against_gt"] == 0.0
    with pytest.raises(TrainError, match="supervised needs ground truth"):
        fit(_cfg(tmp_path, shards["pseudo"], shards["pseudo"], "trainer.fast_dev_run=true", "loss.name=supervised"))


def test_short_run_validates_at_its_last_step_and_exports_the_best_checkpoint(shards, tmp_path):
    """python train.py ... trainer.max_steps=3: the default experiment validates every 200 steps, so only the final
    validation makes the best checkpoint; the run ends by exporting it (the default formats, and the CPU recipes' int8
    network calibrated on the training shards, which comes with the onnx format) under out_dir."""
    formats = list(_compose().export.formats)
    assert _compose().export.int8 is True and _compose("experiment=paper").export.int8 is False
    cfg = _cfg(tmp_path, shards["gt"], shards["gt"], "trainer.max_steps=3", f"export.formats=[{','.join(formats)}]")
    assert cfg.trainer.val_check_interval == 200 and formats == ["onnx", "pt2"]
    trainer = fit(cfg)
    assert trainer.global_step == 3 and trainer.lightning_module.validations == 1
    best = list((tmp_path / "run" / "checkpoints").glob("best-*.ckpt"))
    assert len(best) == 1 and best[0].name.startswith("best-step0000003-")
    export = tmp_path / "run" / "export"
    assert sorted(p.name for p in export.iterdir()) == sorted([METADATA_NAME, *FILE_NAMES.values(), INT8_FILE_NAME])
    metadata = json.loads((export / METADATA_NAME).read_text())
    assert metadata["source_checkpoint"]["path"] == str(best[0].resolve())
    assert set(metadata["files"]) == {*formats, INT8} and max(metadata["parity_max_abs_m"].values()) <= 1e-4
    assert metadata["int8"]["calibration_pairs"] >= 1
    assert metadata["input"]["remove_ground"] is True
    assert {key: metadata["input"][key] for key in ("frame", "ground", "ego_motion")} == {
        key: value
        for key, value in Preprocessing.from_teacher(TEACHER).to_dict().items()
        if key not in ("version", "frame_description")
    }


def test_export_falls_back_to_last_checkpoint_and_says_so(shards, tmp_path, caplog):
    cfg = _cfg(
        tmp_path,
        shards["gt"],
        shards["gt"],
        "trainer.max_steps=2",
        "callbacks.best.save_top_k=0",
        "export.formats=[pt2]",
    )
    with caplog.at_level(logging.WARNING, logger="fastflow3d.training"):
        fit(cfg)
    last = tmp_path / "run" / "checkpoints" / "last.ckpt"
    assert (
        not list(last.parent.glob("best-*"))
        and f"no best checkpoint (no validation ran?): exporting {last}" in caplog.text
    )
    metadata = json.loads((tmp_path / "run" / "export" / METADATA_NAME).read_text())
    assert metadata["source_checkpoint"]["path"] == str(last.resolve()) and list(metadata["files"]) == ["pt2"]
    with pytest.raises(TrainError, match="export.formats: unknown tflite"):
        fit(_cfg(tmp_path, shards["gt"], shards["gt"], "export.formats=[tflite]"))


def test_a_missing_export_package_is_refused_before_training(tmp_path, monkeypatch):
    """Without the export extra a run trained to its end, then failed to export: refused first, before any folder is
    made, naming the package, the fix and the formats that need none (the check itself is monkeypatched: nothing
    is uninstalled)."""
    from fastflow3d.artifact import export
    from fastflow3d.training import trainer

    monkeypatch.setattr(trainer, "missing_packages", lambda formats: ["onnxscript"] if "onnx" in formats else [])
    absent = tmp_path / "none"
    with pytest.raises(TrainError) as refused:
        fit(_cfg(tmp_path, absent, absent, "export.formats=[onnx,pt2]", "export.int8=true"))
    assert str(refused.value) == (
        "export.formats=[onnx,pt2]: the export at the end of training needs onnxscript, not installed here: "
        'pip install "icpflow[export]", or export.formats=[pt2] (torch alone) or export.formats=[] (no export)'
    )
    assert not (tmp_path / "run").exists()
    for formats in ("[pt2]", "[]"):  # nothing missing: on to the data, the next check
        with pytest.raises(TrainError, match="data.train"):
            fit(_cfg(tmp_path, absent, absent, f"export.formats={formats}"))
    # what each format needs, found (not imported) in this environment, which has the export extra
    assert export.missing_packages(["onnx", "pt2"]) == [] and export.missing_packages([]) == []
    monkeypatch.setitem(export.FORMAT_PACKAGES, "pt2", ("torch", "no_such_package_for_pt2"))
    assert export.missing_packages(["onnx", "pt2"]) == ["no_such_package_for_pt2"]


def test_tensorboard_holds_loss_lr_val_metrics_and_bev(shards, tmp_path):
    """A short real run (4 steps, validation every 2): the event file holds train/loss, the learning rate, the
    validation metrics and the BEV image, each validation once (the last step is a scheduled one: no extra)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    cfg = _cfg(
        tmp_path,
        shards["gt"],
        shards["gt"],
        "trainer.max_steps=4",
        "trainer.val_check_interval=2",
        "data.batch_size=1",
        "metrics.bev_every=1",
        "scheduler=constant",
    )
    trainer = fit(cfg)
    assert trainer.lightning_module.validations == 2
    files = list((tmp_path / "run" / "tensorboard").rglob("events.out.tfevents.*"))
    assert len(files) == 1
    events = EventAccumulator(str(files[0].parent), size_guidance={"scalars": 0, "images": 0}).Reload()
    scalars = set(events.Tags()["scalars"])
    assert {"train/loss", "lr-Adam", "val/loss", "val/against_gt"} <= scalars
    categories = ("dynamic_fg", "static_fg", "static_bg")
    assert {f"val/{c}/{m}" for c in categories for m in ("EPE", "AccS", "AccR")} <= scalars
    losses = [event.value for event in events.Scalars("train/loss")]
    assert len(losses) == 4 and all(np.isfinite(losses))
    assert [event.value for event in events.Scalars("lr-Adam")] == pytest.approx([cfg.optim.lr] * 4)
    epe = events.Scalars("val/dynamic_fg/EPE")
    assert len(epe) == 2 and all(0 < event.value < 10 for event in epe)
    images = events.Images("val/bev")
    assert len(images) == 2 and min(images[0].width, images[0].height) > 200
    assert sorted(p.name for p in (tmp_path / "run" / "bev").iterdir()) == [
        "val_step0000002.png",
        "val_step0000004.png",
    ]


def test_epoch_based_run_validates_its_last_batch(shards, tmp_path):
    """2 epochs of 2 batches with validation every 3 batches: batch 3 is validated, and the last one (4) too."""
    trainer = fit(
        _cfg(
            tmp_path,
            shards["gt"],
            shards["gt"],
            "trainer.max_steps=-1",
            "trainer.max_epochs=2",
            "trainer.val_check_interval=3",
            "data.batch_size=1",
            "metrics.bev_every=0",
        )
    )
    assert trainer.global_step == 4 and trainer.current_epoch == 2 and trainer.lightning_module.validations == 2


@pytest.mark.slow
def test_overfit_one_pair_drives_dynamic_epe_down(shards, tmp_path):
    cfg = _cfg(
        tmp_path,
        shards["one"],
        shards["one"],
        "trainer.max_steps=150",
        "trainer.val_check_interval=150",
        "optim.lr=1e-3",
        "scheduler=constant",
        "data.augment=null",  # one pair, memorised as it is
        "loss.weighting=speed",
        "metrics.bev_every=0",
        "metrics.crop=16.0",
    )
    before = L.Trainer(logger=False, enable_progress_bar=False, enable_model_summary=False).validate(
        student_module(OmegaConf.to_container(cfg, resolve=True)), datamodule=_datamodule(cfg), verbose=False
    )[0]
    trainer = fit(cfg)
    after = trainer.callback_metrics["val/dynamic_fg/EPE"].item()
    assert after < before["val/dynamic_fg/EPE"] / 5, (before["val/dynamic_fg/EPE"], after)


def _datamodule(cfg):
    from fastflow3d.training.data import ShardDataModule

    return ShardDataModule(cfg.data.train, cfg.data.val, cfg.data.batch_size, cfg.data.workers)


def test_resume_continues_steps_and_checkpoint_rebuilds_model(shards, tmp_path):
    common = ("trainer.val_check_interval=2", "data.batch_size=1")
    first = fit(_cfg(tmp_path, shards["gt"], shards["gt"], "trainer.max_steps=3", *common))
    last = tmp_path / "run" / "checkpoints" / "last.ckpt"
    assert first.global_step == 3 and torch.load(last, weights_only=True)["global_step"] == 3
    assert list(last.parent.glob("best-*.ckpt"))

    second = fit(_cfg(tmp_path, shards["gt"], shards["gt"], "trainer.max_steps=5", "ckpt_path=last", *common))
    checkpoint = torch.load(last, weights_only=True)
    assert second.global_step == 5 and checkpoint["global_step"] == 5
    assert checkpoint["package_version"] == icpflow.__version__  # as shards and exports record it
    adam_steps = {float(state["step"]) for state in checkpoint["optimizer_states"][0]["state"].values()}
    assert adam_steps == {5.0}  # the optimiser continued: a fresh start would have taken 2 steps

    model, cfg = load_student(last)
    expected = OmegaConf.to_container(
        _cfg(tmp_path, shards["gt"], shards["gt"], "trainer.max_steps=5", "ckpt_path=last", *common), resolve=True
    )
    expected["input"] = second.lightning_module.contract.to_dict()  # the teacher's part from the shards
    batch = expected["data"]["batch_size"] * expected["trainer"]["accumulate_grad_batches"]
    expected["effective_batch"] = batch  # what ran: batch x accumulation x 1 device x 1 node
    expected["trainer"]["precision"] = str(second.precision)  # and the precision trainer.precision=auto chose
    assert second.lightning_module.contract.preprocessing == Preprocessing.from_teacher(TEACHER)
    assert not model.training and cfg == expected
    assert cfg["model"]["cell"] == TINY_MODEL["cell"] and cfg["model"]["stage_channels"] == TINY_MODEL["stage_channels"]
    batch = collate([StudentDataset(shards["gt"])[0]])
    trained = second.lightning_module.model.eval()
    args = (batch["pc0_compensated"], batch["batch0"], batch["pc1"], batch["batch1"], 1)
    with torch.no_grad():
        expected, got = trained(*args)[0], model(*args)[0]
    assert torch.equal(expected, got) and torch.any(expected != 0)


def test_weight_averaging_is_what_checkpoints_hold_and_a_resume_keeps_both(shards, tmp_path):
    """callbacks=ema with decay 1: the average is the weights after the first step, frozen. Checkpoints' state_dict
    (what load_student, eval.py and the export read) is that average, also after a resume that trained on from the
    current weights (current_model_state)."""
    common = ("callbacks=ema", "callbacks.ema.decay=1.0", "trainer.val_check_interval=1", "data.batch_size=1")
    fit(_cfg(tmp_path, shards["gt"], shards["gt"], "trainer.max_steps=1", *common))
    last = tmp_path / "run" / "checkpoints" / "last.ckpt"
    first = torch.load(last, weights_only=True)
    second_trainer = fit(_cfg(tmp_path, shards["gt"], shards["gt"], "trainer.max_steps=3", "ckpt_path=last", *common))
    second = torch.load(last, weights_only=True)
    assert second["global_step"] == 3
    assert {float(state["step"]) for state in second["optimizer_states"][0]["state"].values()} == {3.0}
    weights = [key for key in first["state_dict"] if key.endswith("weight")]
    for key in weights:
        assert torch.equal(second["state_dict"][key], first["state_dict"][key]), key  # the frozen average
        assert torch.equal(first["current_model_state"][key], first["state_dict"][key]), key
    assert any(not torch.equal(second["current_model_state"][k], second["state_dict"][k]) for k in weights)
    (best,) = last.parent.glob("best-*.ckpt")
    assert all(
        torch.equal(torch.load(best, weights_only=True)["state_dict"][k], first["state_dict"][k]) for k in weights
    )
    model, _ = load_student(last)
    averaged = {k[len("model.") :]: v for k, v in first["state_dict"].items() if k.startswith("model.")}
    assert all(torch.equal(model.state_dict()[k], averaged[k]) for k in averaged)
    # the end of fit leaves the average in the module too (what an in-process caller would use)
    trained = second_trainer.lightning_module.model.state_dict()
    assert all(torch.equal(trained[k], averaged[k]) for k in averaged)


def test_a_run_bounded_by_time_alone_is_refused_before_it_starts(shards, tmp_path):
    """The schedule is laid out over the run's steps: max_steps=-1 with max_epochs=-1 gave an OverflowError deep in
    Lightning (found on a GPU run of experiment=paper with max_time); now one line before any work."""
    unbounded = ("trainer.max_steps=-1", "trainer.max_epochs=-1", "trainer.max_time=00:00:01:00")
    with pytest.raises(TrainError, match=r"^trainer.max_steps=-1 and trainer.max_epochs=-1: the learning-rate"):
        fit(_cfg(tmp_path / "run", shards["gt"], shards["gt"], *unbounded))
    assert not (tmp_path / "run").exists()


def test_ckpt_path_last_without_checkpoint(shards, tmp_path):
    with pytest.raises(TrainError, match="last.ckpt does not exist"):
        fit(_cfg(tmp_path, shards["gt"], shards["gt"], "ckpt_path=last"))


def test_load_student_rejects_other_files(tmp_path):
    text = tmp_path / "notes.ckpt"
    text.write_text("not a checkpoint")
    with pytest.raises(CheckpointError, match=r"notes.ckpt: not a readable torch checkpoint"):
        load_student(text)
    plain = tmp_path / "plain.ckpt"
    torch.save({"state_dict": {}}, plain)
    with pytest.raises(CheckpointError, match=r"plain.ckpt: not a FastFlow3D student checkpoint"):
        load_student(plain)
    wrong = tmp_path / "wrong.ckpt"
    model_cfg = {
        "_target_": "fastflow3d.network.model.FastFlow3D",
        "x_range": [-4.0, 4.0],
        "y_range": [-4.0, 4.0],
        "cell": 1.0,
        "stage_channels": [8, 16, 32],
    }
    torch.save(
        {"state_dict": {"model.head.0.weight": torch.zeros(2, 2)}, "hyper_parameters": {"cfg": {"model": model_cfg}}},
        wrong,
    )
    with pytest.raises(CheckpointError, match=r"wrong.ckpt: weights do not fit"):
        load_student(wrong)
    with pytest.raises(CheckpointError, match="does not exist"):
        load_student(tmp_path / "missing.ckpt")


@pytest.mark.parametrize("world", [1, 2])
def test_validation_shares_of_several_processes_hold_each_sample_once(shards, world):
    """Issue 34.1 (c), the data side: with several processes each rank validates its share, together every sample of
    the val set exactly once (Lightning's own sampler pads the shares with repeats, which the summed metrics would
    count twice); shares differ by at most one sample."""
    from types import SimpleNamespace

    from fastflow3d.training.data import ShardDataModule

    seen = []
    for rank in range(world):
        module = ShardDataModule(shards["gt"], shards["gt"], batch_size=2, workers=0)
        module.trainer = SimpleNamespace(world_size=world, global_rank=rank)
        module.setup("validate")
        seen.append([sample_id for batch in module.val_dataloader() for sample_id in batch["sample_id"]])
    everything = StudentDataset(shards["gt"]).shards.sample_ids
    assert sorted(sum(seen, [])) == sorted(everything) and len(everything) >= world
    assert max(map(len, seen)) - min(map(len, seen)) <= 1
