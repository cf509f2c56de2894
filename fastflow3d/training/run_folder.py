"""The run folder of ``train.py`` (``out_dir``) and what a run may do with it: one run at a time (its lock), a fresh
start that would overwrite another run's checkpoints refused (``overwrite=true`` removes them), and a resume
(``ckpt_path=last|auto|<file>``) only from a checkpoint of the same network and settings; what a stopped run leaves
to resume from, in words. :class:`TrainError` is the one-line error of a run that cannot start."""

from __future__ import annotations

import contextlib
import logging
from pathlib import Path
from typing import TYPE_CHECKING

from omegaconf import DictConfig, OmegaConf

from fastflow3d.artifact.checkpoint import CheckpointError, read_checkpoint
from icpflow.core.atomic import FolderInUse, folder_lock
from icpflow.core.errors_and_signals import launching_process, os_error_line
from icpflow.core.files import not_a_file

if TYPE_CHECKING:
    from fastflow3d.training.student_module import StudentModule

log = logging.getLogger(__package__)  # the training room's logger: its console lines read "training: ..."


class TrainError(RuntimeError):
    """A training run cannot start, or its final export failed. The message is one line."""


def resolve_ckpt_path(cfg: DictConfig, module: StudentModule) -> str | None:
    """The checkpoint to resume from: None, ``<checkpoint_dir>/last.ckpt`` for ``last`` (and for ``auto`` where it
    exists: a job a cluster requeues after a pre-emption runs the same command, first afresh, then resuming), or the
    given file; it must hold weights of ``module``'s network (same names and shapes), else one line naming the
    settings that differ."""
    value = cfg.get("ckpt_path")
    if value == "auto":
        value = "last" if (Path(cfg.checkpoint_dir) / "last.ckpt").is_file() else None
        if launching_process():
            log.info(
                "ckpt_path=auto: %s", f"resuming from {cfg.checkpoint_dir}/last.ckpt" if value else "starting afresh"
            )
    if not value:
        return None
    path = Path(cfg.checkpoint_dir) / "last.ckpt" if value == "last" else Path(value)
    if (refused := not_a_file(path)) is not None:
        raise TrainError(f"ckpt_path={value}: {refused}")
    if not path.is_file():
        raise TrainError(
            f"ckpt_path={value}: {path} does not exist (nothing to resume; leave ckpt_path unset to start afresh)"
        )
    try:
        checkpoint = read_checkpoint(path)
    except CheckpointError as error:
        raise TrainError(
            f"ckpt_path={value}: {error}; give another checkpoint, or leave ckpt_path unset to start afresh"
        ) from None
    expected = {name: tuple(tensor.shape) for name, tensor in module.state_dict().items()}
    state = checkpoint.get("state_dict")
    found = {name: tuple(tensor.shape) for name, tensor in state.items()} if isinstance(state, dict) else {}
    if found != expected:
        hparams = checkpoint.get("hyper_parameters")
        saved = (hparams.get("cfg") or {}).get("model") if isinstance(hparams, dict) else None
        ours = OmegaConf.to_container(cfg.model, resolve=True)
        differ = [
            f"model.{key}={saved.get(key)} (this run: {ours.get(key)})"
            for key in sorted(set(saved or {}) | set(ours))
            if isinstance(saved, dict) and saved.get(key) != ours.get(key)
        ]
        what = ", ".join(differ) if differ else "its weights have other names or shapes"
        raise TrainError(
            f"ckpt_path={value}: {path} holds another network: {what}; resume with the model settings it was "
            "trained with, or leave ckpt_path unset to start afresh"
        )
    check_resume_settings(module.hparams["cfg"], checkpoint, value, path)
    return str(path)


def kept_checkpoint(cfg: DictConfig) -> str:
    """What a run stopped at once leaves to resume from, in words."""
    last = Path(cfg.checkpoint_dir) / "last.ckpt"
    try:
        step = read_checkpoint(last).get("global_step")
    except CheckpointError:
        return "nothing saved; rerun the same command"
    return f"{last} (step {step}) is kept; to resume, rerun the same command with ckpt_path=last"


@contextlib.contextmanager
def run_folder(cfg: DictConfig):
    """One run per ``out_dir``: its lock (``icpflow.core.atomic.folder_lock``) for the whole run, taken by the launching
    process only; a second run into the folder is refused in one line naming the holder's pid."""
    with contextlib.ExitStack() as stack:
        if launching_process():
            try:
                stack.enter_context(folder_lock(cfg.out_dir, "train.py"))
            except FolderInUse as error:
                raise TrainError(str(error)) from None
            except OSError as error:
                raise TrainError(os_error_line(error)) from None
        yield


def check_fresh_start(cfg: DictConfig) -> None:
    """A run without ``ckpt_path`` into a folder that holds ``last.ckpt`` would overwrite another run's checkpoints:
    refused in one line, unless ``overwrite=true``: then the folder's checkpoints are removed first, said in the log,
    where each has a name the run's callbacks write; another ``.ckpt`` there (a user's) refuses the start before
    anything is removed."""
    if cfg.get("ckpt_path"):  # auto included: it resumes where last.ckpt exists
        return
    folder = Path(cfg.checkpoint_dir)
    last = folder / "last.ckpt"
    if not last.is_file():
        return
    if not cfg.get("overwrite"):
        raise TrainError(
            f"{folder} holds another run's checkpoints ({last.name}); resume it with ckpt_path=last, start afresh "
            "with overwrite=true (its checkpoints are removed), or give another out_dir"
        )
    old = sorted(folder.glob("*.ckpt"))
    prefixes = checkpoint_prefixes(cfg)
    foreign = [path.name for path in old if path.name != last.name and not path.name.startswith(prefixes)]
    if foreign:  # claimed by name: a checkpoint the user put there is not the previous run's to remove
        raise TrainError(
            f"{folder}: {foreign[0]} is not a checkpoint a run names (last.ckpt, {', '.join(p + '*' for p in prefixes)}"
            "); nothing was removed: move it, or give another out_dir"
        )
    for path in old:
        path.unlink()
    log.warning("overwrite=true: removed %d checkpoint(s) of the previous run in %s", len(old), folder)


def checkpoint_prefixes(cfg: DictConfig) -> tuple[str, ...]:
    """The fixed beginnings of the checkpoint names the run's callbacks write (their ``filename`` up to its first
    field, ``best-step`` by default; Lightning's ``epoch=`` where one names none)."""
    prefixes = [
        str(block.get("filename") or "epoch=").split("{")[0]
        for block in (cfg.get("callbacks") or {}).values()
        if isinstance(block, DictConfig) and str(block.get("_target_", "")).endswith("ModelCheckpoint")
    ]
    return tuple(prefix for prefix in prefixes if prefix) or ("epoch=",)


#: data settings that may differ on a resume (where the files are, how they are read)
RESUME_FREE_DATA = ("train", "val", "workers")


def _differences(saved: dict, ours: dict, prefix: str, skip=()) -> list[str]:
    """``prefix.key=<saved> (this run: <ours>)`` for each key whose value differs (nested dicts flattened)."""
    out = []
    for key in sorted(set(saved) | set(ours)):
        if key in skip:
            continue
        a, b = saved.get(key), ours.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += _differences(a, b, f"{prefix}.{key}")
        elif a != b:
            out.append(f"{prefix}.{key}={a} (this run: {b})")
    return out


def check_resume_settings(ours: dict, checkpoint: dict, value: str, path: Path) -> None:
    """A resume with other model or data settings than the checkpoint's is refused, one line naming each
    difference; differing optimiser or schedule settings are not applied (the checkpoint's optimiser and schedule
    state continue): said in the log, naming them. ``ours``: this run's resolved config as the module holds it
    (its ``input`` included), compared with the one the checkpoint stores."""
    hparams = checkpoint.get("hyper_parameters")
    saved = (hparams.get("cfg") or {}) if isinstance(hparams, dict) else {}
    if not isinstance(saved, dict) or not saved:
        return
    differ = _differences(saved.get("model") or {}, ours.get("model") or {}, "model")
    differ += _differences(saved.get("data") or {}, ours.get("data") or {}, "data", RESUME_FREE_DATA)
    if "input" in saved:  # checkpoints of older versions stored it under data (compared above)
        differ += _differences(saved["input"] or {}, ours.get("input") or {}, "input")
    if differ:
        raise TrainError(
            f"ckpt_path={value}: {path} was trained with other settings: {'; '.join(differ)}; resume with its "
            "settings, or leave ckpt_path unset to start afresh"
        )
    moved = [
        f"data.{key}={(saved.get('data') or {}).get(key)} (this run: {(ours.get('data') or {}).get(key)})"
        for key in ("train", "val")
        if (saved.get("data") or {}).get(key) != (ours.get("data") or {}).get(key)
    ]
    if moved:  # allowed (a folder moved, a cluster's other mount), but never silent
        log.warning("resuming %s with other data than it was trained on: %s", path.name, "; ".join(moved))
    kept = _differences(saved.get("optim") or {}, ours.get("optim") or {}, "optim")
    kept += _differences(saved.get("scheduler") or {}, ours.get("scheduler") or {}, "scheduler")
    if kept:
        log.warning(
            "resuming %s: the optimiser and schedule state continue from the checkpoint; not applied: %s",
            path.name,
            "; ".join(kept),
        )
