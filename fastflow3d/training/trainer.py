"""``train.py``: from the Hydra config (``conf/train.yaml``) to a Lightning fit of the student on pseudo-flow shards,
ending with the export of the best checkpoint.

Everything a run writes lands under ``out_dir``: ``checkpoints/`` (best on validation dynamic EPE and
``last.ckpt``), ``tensorboard/``, ``bev/``, ``export/`` and ``hydra/``. ``ckpt_path=last`` resumes from
``<checkpoint_dir>/last.ckpt`` (optimiser, schedule, step count and the position in the training order included),
``ckpt_path=auto`` does so where it exists and starts afresh otherwise (a cluster job's requeue); any other value is a
checkpoint file (the run folder's rules: ``fastflow3d.training.run_folder``).
The saved config's ``input`` holds the input contract (``fastflow3d.network.contract``: the height frame, ground removal
and its settings, the ego-motion settings, the grid) that the Predictor uses on raw scans.
"""

from __future__ import annotations

import logging
from pathlib import Path

import lightning as L
from hydra.utils import instantiate
from lightning.fabric.plugins.environments import SLURMEnvironment
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.utilities import rank_zero_only
from omegaconf import DictConfig, OmegaConf

from fastflow3d.artifact.checkpoint import build_student
from fastflow3d.artifact.export import export_checkpoint, missing_packages
from fastflow3d.artifact.file_format import FORMATS
from fastflow3d.network.contract import ContractError, InputContract, read_grid
from fastflow3d.training.callbacks import AtomicCheckpointIO, LastCheckpoint, ModelSize, TrainingStopped, progress_bar
from fastflow3d.training.data import DataError, ShardDataModule, StudentDataset, labeller_contract
from fastflow3d.training.precision import choose_precision
from fastflow3d.training.run_folder import (
    TrainError,
    check_fresh_start,
    kept_checkpoint,
    resolve_ckpt_path,
    run_folder,
)
from fastflow3d.training.student_module import NonFiniteLoss, StudentModule
from icpflow.core.errors_and_signals import Stop, one_line, os_error_line, signal_words, stop_on_signals
from icpflow.core.settings import check_config
from icpflow.shards.verify import ShardError

log = logging.getLogger(__package__)  # the training room's logger: its console lines read "training: ..."


def check_data(cfg: DictConfig) -> dict[str, int]:
    """Both shard directories hold samples (else one line saying how to create them), every shard they list is
    complete and valid (else one line naming it: the checks ``label.py`` makes before it skips a shard);
    supervised needs gt; ``out_dir`` is not one of them. Returns the samples of each (``train``, ``val``)."""
    if (Path(cfg.out_dir) / "index.json").is_file():  # data.train itself, or another label folder
        raise TrainError(
            f"out_dir={cfg.out_dir} holds label.py's shards (index.json): checkpoints would go among the labels; "
            "give another folder"
        )
    for key in ("train", "val"):
        if not cfg.data[key]:
            raise TrainError(f"data.{key} is empty; give a label folder (a path)")
    same = Path(cfg.data.train).resolve() == Path(cfg.data.val).resolve()
    if same:
        log.warning("data.val is data.train (%s): validation scores the training samples", cfg.data.train)
    ids, counts = {}, {}
    for key, split in (("train", "train"), ("val", "val")):
        path = cfg.data[key]
        try:
            dataset = StudentDataset(path)
        except DataError as error:
            raise TrainError(
                f"data.{key}: {error}; label a dataset into it first, e.g. "
                f"`python label.py split={split} out_dir={path}`"
            ) from None
        except ValueError as error:  # a damaged index.json
            raise TrainError(
                f"data.{key}: {one_line(error)}; rerun the label.py command that wrote it "
                f"(same out_dir={path}): it rebuilds the index"
            ) from None
        try:
            dataset.shards.verify()
        except ShardError as error:
            raise TrainError(
                f"data.{key}: {error}; rerun the label.py command that wrote it (same out_dir={path}): "
                "it redoes damaged shards"
            ) from None
        if dataset.shards.incomplete():  # trained on as it is, but said: a stopped label.py is no silent subset
            log.warning("data.%s: %s", key, dataset.shards.incomplete())
        if key == "train" and cfg.loss.name == "supervised" and "gt" not in dataset[0]:
            raise TrainError(f"loss.name=supervised needs ground truth, but data.train={path} has none")
        ids[key] = set(dataset.shards.sample_ids)
        counts[key] = len(dataset)
    shared = ids["train"] & ids["val"]
    if shared and not same:
        log.warning(
            "data.val shares %d of its %d sample ids with data.train (e.g. %s): validation scores samples trained on",
            len(shared),
            len(ids["val"]),
            sorted(shared)[0],
        )
    return counts


def training_contract(cfg: DictConfig) -> InputContract:
    """The input contract saved with the model (``fastflow3d.network.contract``): the height frame, ground and
    ego-motion settings of the teacher that labelled ``data.train`` (its shards' labeller config),
    ``data.remove_ground`` and the grid of ``model``."""
    try:
        grid = read_grid(OmegaConf.to_container(cfg.model, resolve=True), "model")
        return labeller_contract(cfg.data.train, bool(cfg.data.remove_ground), grid)
    except ContractError as error:
        raise TrainError(one_line(error)) from None
    except DataError as error:
        raise TrainError(f"data.train: {error}") from None


def build_module(cfg: DictConfig, contract: InputContract, config: dict) -> StudentModule:
    """The LightningModule of ``cfg.module`` (``conf/train.yaml``) with the network of ``cfg.model`` and
    ``contract``; the whole resolved ``config`` is saved in its checkpoints (``hparams.cfg``; given here, after
    instantiation: Hydra would instantiate the ``_target_``s inside it, and convert the contract into a dict)."""
    from hydra.errors import InstantiationException

    try:  # a partial: the network and the contract reach the module as the objects they are
        make = instantiate(cfg.module, _partial_=True)
    except InstantiationException as error:  # Hydra's wrapper: the one-line error is the cause
        raise TrainError(one_line(error.__cause__ or error)) from None
    try:
        module = make(model=build_student(config["model"]), contract=contract)
    except ValueError as error:
        raise TrainError(one_line(error)) from None
    module.save_hyperparameters({"cfg": config})
    return module


def check_length(cfg: DictConfig) -> None:
    """A run's length in steps or epochs: the learning-rate schedule is laid out over it (``trainer.max_time``
    can stop a run earlier but gives no length)."""
    if cfg.trainer.get("max_steps", -1) == -1 and cfg.trainer.get("max_epochs") == -1:
        raise TrainError(
            "trainer.max_steps=-1 and trainer.max_epochs=-1: the learning-rate schedule needs the run's length; "
            "set one of them (trainer.max_time may still stop the run earlier)"
        )


def export_formats(cfg: DictConfig) -> tuple[str, ...]:
    """``export.formats`` checked before training, their names and the packages they need (either would otherwise
    fail only at the end, after the whole run: "training finished but exporting ... failed")."""
    formats = tuple(cfg.export.formats or ())
    unknown = [name for name in formats if name not in FORMATS]
    if unknown:
        raise TrainError(
            f"export.formats: unknown {', '.join(map(str, unknown))}; use a list of "
            f"{', '.join(FORMATS)}, or [] for no export"
        )
    missing = missing_packages(formats)
    if missing:
        raise TrainError(
            f"export.formats=[{','.join(formats)}]: the export at the end of training needs {', '.join(missing)}, "
            'not installed here: pip install "icpflow[export]", or export.formats=[pt2] (torch alone) or '
            "export.formats=[] (no export)"
        )
    return formats


def build_trainer(cfg: DictConfig) -> L.Trainer:
    """The Lightning Trainer of ``cfg.trainer`` (Trainer keyword arguments; ``precision: auto`` chosen for this host
    and said, ``fastflow3d.training.precision``) with the configured logger and callbacks
    (``LastCheckpoint`` after the other checkpoint callbacks, so it saves their state after theirs) and checkpoint
    files written atomically; in a SLURM job, Lightning's SLURM environment without its SIGUSR1 auto-requeue."""
    logger = instantiate(cfg.logger) if cfg.get("logger") else False
    callbacks = [instantiate(callback) for callback in (cfg.get("callbacks") or {}).values()]
    callbacks.sort(key=lambda callback: isinstance(callback, LastCheckpoint))
    trainer_kwargs = OmegaConf.to_container(cfg.trainer, resolve=True)
    requested = trainer_kwargs.get("precision") or "32-true"
    precision, line, emulated = choose_precision(requested, str(trainer_kwargs.get("accelerator", "auto")))
    trainer_kwargs["precision"] = precision
    if rank_zero_only.rank == 0:
        (log.warning if emulated else log.info)(line)
    for name, ours in (("enable_progress_bar", True), ("enable_model_summary", False)):
        if trainer_kwargs.get(name) is None:  # Lightning's default (None): ours
            trainer_kwargs[name] = ours
    if trainer_kwargs["enable_progress_bar"]:  # the console: icpflow.core.console, fastflow3d.training.callbacks
        callbacks.append(progress_bar())
    if not trainer_kwargs["enable_model_summary"]:
        callbacks.append(ModelSize())
    callbacks.sort(key=lambda callback: isinstance(callback, LastCheckpoint))
    plugins = trainer_kwargs.pop("plugins", None) or [AtomicCheckpointIO()]
    if SLURMEnvironment.detect():  # one way to stop and resume on SLURM: SIGTERM saves last.ckpt (LastCheckpoint),
        plugins.append(SLURMEnvironment(auto_requeue=False))  # ckpt_path=auto resumes; not Lightning's SIGUSR1 requeue
    return L.Trainer(
        **trainer_kwargs, logger=logger, callbacks=callbacks, plugins=plugins, default_root_dir=cfg.out_dir
    )


def accumulation(effective: int, batch: int, devices: int, nodes: int) -> int:
    """The batches to accumulate so that ``batch`` samples per device on ``devices`` devices of ``nodes`` nodes make
    an ``effective`` batch; TrainError (one line) when they cannot."""
    parts = batch * devices * nodes
    if effective % parts:
        raise TrainError(
            f"effective_batch={effective} is not a multiple of data.batch_size x devices x nodes = {batch} x "
            f"{devices} x {nodes} = {parts}; choose a batch size and devices that divide it"
        )
    return effective // parts


def settle_batch(cfg: DictConfig, trainer: L.Trainer) -> tuple[int, str]:
    """The run's effective batch (samples per optimiser step over every device and node) and its line; with
    ``effective_batch`` set, ``trainer.accumulate_grad_batches`` is set to reach it on this trainer's devices."""
    batch, devices, nodes = int(cfg.data.batch_size), int(trainer.num_devices), int(trainer.num_nodes)
    if cfg.get("effective_batch"):
        trainer.accumulate_grad_batches = accumulation(int(cfg.effective_batch), batch, devices, nodes)
    accumulated = int(trainer.accumulate_grad_batches)
    effective = batch * accumulated * devices * nodes
    line = (
        f"effective batch {effective} = {batch} per device x {accumulated} accumulated x {devices} device(s) x "
        f"{nodes} node(s)"
    )
    return effective, line


def best_checkpoint(trainer: L.Trainer) -> Path | None:
    """The best checkpoint of the first monitoring ModelCheckpoint, if it exists."""
    for callback in trainer.checkpoint_callbacks:
        if isinstance(callback, ModelCheckpoint) and callback.best_model_path:
            path = Path(callback.best_model_path)
            return path if path.is_file() else None
    return None


def export_best(trainer: L.Trainer, cfg: DictConfig, formats: tuple[str, ...]) -> Path | None:
    """Export the best checkpoint (``last.ckpt`` when there is none, with a warning) to ``export.dir``; returns the
    directory, or None when there is nothing to do (no formats, fast_dev_run, interrupted run, not rank 0)."""
    if not formats or trainer.fast_dev_run or trainer.interrupted or not trainer.is_global_zero:
        return None
    source = best_checkpoint(trainer) or Path(cfg.checkpoint_dir) / "last.ckpt"
    if not source.is_file():
        raise TrainError(f"training ended with no checkpoint to export in {cfg.checkpoint_dir}")
    if source.name == "last.ckpt":
        log.warning("no best checkpoint (no validation ran?): exporting %s instead", source)
    log.info("exporting %s (%s) to %s: about 20 s ...", source.name, ", ".join(formats), cfg.export.dir)
    try:
        int8 = bool(cfg.export.get("int8", False)) and "onnx" in formats  # the int8 network of the ONNX one
        out_dir = export_checkpoint(source, cfg.export.dir, formats, int8=int8)
    except (ValueError, RuntimeError, OSError) as error:
        cause = os_error_line(error) if isinstance(error, OSError) else one_line(error)
        raise TrainError(
            f"training finished but exporting {source} failed: {cause} "
            f"(retry with `python export.py checkpoint={source}`)"
        ) from None
    except Stop as stop:
        raise Stop(
            stop.signum,
            f"{signal_words(stop.signum)} while exporting {source} (training had finished; {cfg.export.dir} is as "
            f"it was): export it with `python export.py checkpoint={source}`",
        ) from None
    log.info("exported %s (%s) to %s", source.name, ", ".join(formats), out_dir)
    return out_dir


def check_sizes(cfg: DictConfig, trainer: L.Trainer, counts: dict[str, int], effective: int) -> None:
    """What the data cannot give, refused in one line before any process starts: fewer samples than processes
    (each process of a DDP run needs one of train and of val), or an ``effective_batch`` set larger than the
    training samples (each step would see fewer than it says)."""
    processes = int(trainer.num_devices) * int(trainer.num_nodes)
    for key in ("train", "val"):
        if counts[key] < processes:
            raise TrainError(
                f"data.{key} holds {counts[key]} sample(s), fewer than the {processes} processes (trainer.devices x "
                "trainer.num_nodes): each needs one; use fewer devices or label more samples"
            )
    if cfg.get("effective_batch") and effective > counts["train"]:
        raise TrainError(
            f"effective_batch={effective} is more than the {counts['train']} training samples: each step would see "
            f"{counts['train']}; choose effective_batch <= {counts['train']} or label more samples"
        )


def fit(cfg: DictConfig) -> L.Trainer:
    """Train the student as ``cfg`` says, then export its best checkpoint; returns the Trainer after ``fit``.

    Raises TrainError (one line) if it cannot start, if a file cannot be written (a full or read-only disk: the
    checkpoints already written are kept) or if the export fails; ``icpflow.core.errors_and_signals.Stop`` on SIGTERM or
    SIGINT: in the training loop after saving ``last.ckpt`` at the current step
    (``fastflow3d.training.callbacks.LastCheckpoint``), elsewhere at once; its message says what was kept and how to
    resume.
    """
    check_config(cfg)  # the schema's rules (fastflow3d.training.options.TrainOptions)
    check_length(cfg)
    formats = export_formats(cfg)  # before the run folder: a missing package is refused before anything is written
    with stop_on_signals(), run_folder(cfg):
        counts = check_data(cfg)
        plain = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
        contract = training_contract(cfg)
        plain["input"] = contract.to_dict()
        L.seed_everything(int(cfg.seed), workers=True, verbose=False)
        module = build_module(cfg, contract, plain)
        ckpt_path = resolve_ckpt_path(cfg, module)
        check_fresh_start(cfg)
        if cfg.compile:
            module.model.compile(dynamic=True)
        data = plain["data"]
        datamodule = ShardDataModule.from_config(data, module.contract, int(cfg.seed))
        trainer = build_trainer(cfg)
        effective, line = settle_batch(cfg, trainer)
        check_sizes(cfg, trainer, counts, effective)
        module.hparams["cfg"]["effective_batch"] = effective  # the logged and saved config say it, and the
        module.hparams["cfg"]["trainer"]["precision"] = str(trainer.precision)  # precision that auto chose
        if trainer.is_global_zero:
            log.info(line)
        try:
            trainer.fit(module, datamodule=datamodule, ckpt_path=ckpt_path, weights_only=True)
        except TrainingStopped:
            raise
        except NonFiniteLoss as error:
            raise TrainError(f"{error}; {kept_checkpoint(cfg)}") from None
        except Stop as stop:  # outside the training loop (set-up, sanity check), or a second signal: at once
            raise Stop(stop.signum, f"{signal_words(stop.signum)}; {kept_checkpoint(cfg)}") from None
        except OSError as error:
            last = Path(cfg.checkpoint_dir) / "last.ckpt"
            resume = f"; then resume with ckpt_path=last ({last} is kept)" if last.is_file() else ""
            raise TrainError(f"{os_error_line(error)}{resume}") from None
        export_best(trainer, cfg, formats)
    return trainer
