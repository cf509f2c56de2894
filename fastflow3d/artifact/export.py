"""Export a trained FastFlow3D (``fastflow3d.artifact.file_format``: ONNX and a ``torch.export`` program, plus
metadata) and check the parity of each exported file against eager PyTorch before it is kept.

Every export is loaded back through ``fastflow3d.artifact.engines.load_network`` (the opener the predictor uses; ONNX
in ONNX Runtime's default CPU session) and run on random clouds of
several sizes; one that differs from eager by more than :data:`PARITY_TOLERANCE` metres, or whose validity mask
differs, is refused. ONNX uses the dynamo exporter: the legacy exporter mis-exports scatter ops without a warning.
On request (``int8``) the ONNX network is also quantised (``fastflow3d.artifact.quantize``), calibrated on labelled
shards, and compared with the float32 one.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import logging
import os
import sys
import warnings
from pathlib import Path

import numpy as np
import torch

from fastflow3d.artifact.checkpoint import load_student
from fastflow3d.artifact.engines import load_network
from fastflow3d.artifact.file_format import (
    FILE_NAMES,
    FORMATS,
    INT8,
    INT8_FILE_NAME,
    LEGACY_FILE_NAMES,
    METADATA_NAME,
    SingleSampleNet,
    network_metadata,
    sha256_file,
    write_metadata,
)
from fastflow3d.artifact.quantize import INT8_TOLERANCE, calibration_pairs, int8_difference, write_int8
from fastflow3d.artifact.writers import WRITERS, onnx_opset
from fastflow3d.network.contract import ContractError, InputContract, upgrade
from fastflow3d.network.model import FastFlow3D
from icpflow.core.atomic import atomic_directory
from icpflow.core.errors_and_signals import Stop, exit_status, one_line, os_error_line, signal_words, stop_on_signals
from icpflow.core.files import not_a_file
from icpflow.core.stops import raise_stop_behind

PARITY_TOLERANCE = 1e-4  # metres, max abs difference between an export and eager

#: the packages each format's export needs beyond torch (the ``export`` extra): the dynamo ONNX exporter (onnxscript,
#: onnx), the parity check and the int8 network's calibration (onnxruntime); a torch.export program needs none
FORMAT_PACKAGES = {"onnx": ("onnx", "onnxscript", "onnxruntime"), "pt2": ()}


def missing_packages(formats) -> list[str]:
    """The packages of :data:`FORMAT_PACKAGES` that exporting ``formats`` needs and that cannot be imported here
    (found, not imported: checking costs nothing)."""
    needed = dict.fromkeys(name for kind in formats for name in FORMAT_PACKAGES.get(kind, ()))
    return [name for name in needed if importlib.util.find_spec(name) is None]


class ExportError(ValueError):
    """An export that cannot be made or that disagrees with eager. The message is one line."""


def check_inputs(model: FastFlow3D, n0: int, n1: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Two uniform random clouds over the grid and a 10 % margin around it (so some points fall outside)."""
    gen = torch.Generator().manual_seed(seed)
    grid = model.grid
    low = torch.tensor([grid.x_range[0], grid.y_range[0], grid.z_range[0]], dtype=torch.float32)
    high = torch.tensor([grid.x_range[1], grid.y_range[1], grid.z_range[1]], dtype=torch.float32)
    low, high = low - 0.1 * (high - low), high + 0.1 * (high - low)
    return tuple(torch.rand(n, 3, generator=gen) * (high - low) + low for n in (n0, n1))


#: (N0, N1, seed) of the clouds every export is checked on; the first one is also the tracing example
CHECK_SIZES = ((3000, 2500, 0), (257, 4100, 1), (6000, 40, 2))


@contextlib.contextmanager
def quiet_exporters():
    """Silence the exporters' progress logs and deprecation warnings for the duration (levels are restored)."""
    loggers = [logging.getLogger(name) for name in ("torch.onnx", "onnxscript", "onnx_ir")]
    levels = [logger.level for logger in loggers]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", (DeprecationWarning, FutureWarning))
        for logger in loggers:
            logger.setLevel(logging.ERROR)
        try:
            yield
        finally:
            for logger, level in zip(loggers, levels):
                logger.setLevel(level)


def measure_parity(net: SingleSampleNet, runner, contract: InputContract | None = None) -> float:
    """Max abs difference (m) of ``runner``'s residual (numpy in, numpy out) against eager on :data:`CHECK_SIZES`,
    twice per pair of clouds: on the whole clouds (the validity masks must match) and on what the input
    ``contract`` hands the network (``InputContract.prepare``: the rows inside the grid), where it must match eager's
    answer for those rows (points outside the grid change nothing)."""
    contract = contract or InputContract(remove_ground=False, grid=net.model.grid)
    worst = 0.0
    for n0, n1, seed in CHECK_SIZES:
        pc0, pc1 = check_inputs(net.model, n0, n1, seed + 100)
        with torch.no_grad():
            expected, valid = net(pc0, pc1)
        residual, got_valid = runner(pc0.numpy(), pc1.numpy())
        if np.shape(residual) != tuple(expected.shape) or not np.array_equal(got_valid, valid.numpy()):
            raise ExportError(f"export disagrees with eager on N0={n0}, N1={n1}: shape or validity mask differs")
        pair = contract.prepare(pc0.numpy(), pc1.numpy(), np.eye(4), np.zeros(n0, bool), np.zeros(n1, bool))
        cropped, _ = runner(pair.network0, pair.network1)
        results = (residual, expected.numpy()), (cropped, expected.numpy()[pair.rows0])
        for got, wanted in results:
            if not (np.isfinite(got).all() and np.isfinite(wanted).all()):  # max(0.0, nan) would be 0.0
                raise ExportError(f"export gives non-finite flow on N0={n0}, N1={n1} (NaN or Inf weights?)")
            worst = max(worst, float(np.abs(got - wanted).max(initial=0.0)))
    return worst


def export_model(
    model: FastFlow3D,
    out_dir: str | os.PathLike,
    formats=FORMATS,
    *,
    model_config: dict | None = None,
    checkpoint=None,
    contract: InputContract | None = None,
    tolerance: float = PARITY_TOLERANCE,
    int8_pairs: tuple[list, list] | None = None,
) -> dict:
    """Export ``model`` (eval mode is set) in ``formats`` to ``out_dir``; returns the metadata written.

    The files are built in a temporary folder next to ``out_dir`` and swapped in whole (``icpflow.core.atomic``):
    ``out_dir`` holds the previous export or the new one, never a part (a full disk, a signal, a failed check leave
    it as it was). Each export is loaded back and compared with eager on random clouds of several sizes; an export
    off by more than ``tolerance`` metres raises :class:`ExportError` and is not kept.

    ``int8_pairs``: ``(calibration, check)`` network inputs (``fastflow3d.artifact.quantize.calibration_pairs``):
    the ONNX network is also written with int8 convolutions (``fastflow3d.int8.onnx``, ``files.onnx_int8``), its
    difference from the float32 one on the check pairs in ``metadata["int8"]``; more than ``INT8_TOLERANCE`` on
    average raises :class:`ExportError` and nothing is kept.
    """
    formats = tuple(formats)
    unknown = [name for name in formats if name not in FORMATS]
    if unknown or not formats:
        raise ExportError(f"unknown export format(s) {unknown or formats}; use {', '.join(FORMATS)} or all")
    if int8_pairs is not None and "onnx" not in formats:
        raise ExportError("int8 quantises the ONNX network: export the onnx format too (format=all or onnx)")
    out_dir = Path(out_dir)
    check_replaceable(out_dir)
    net = SingleSampleNet(model.eval()).eval()
    example = check_inputs(model, *CHECK_SIZES[0])
    metadata = network_metadata(model, model_config, checkpoint, contract)
    metadata["files"], metadata["parity_max_abs_m"] = {}, {}
    with atomic_directory(out_dir) as build:  # built aside, swapped in whole: a failure leaves out_dir as it was
        for name in formats:
            path = build / FILE_NAMES[name]
            with quiet_exporters():
                try:
                    WRITERS[name](net, path, example)
                except ImportError as error:  # the ONNX exporter without onnxscript
                    raise_stop_behind(error)
                    raise ExportError(
                        "ONNX export needs onnx, onnxscript and onnxruntime: pip install 'icpflow[export]'"
                    ) from None
                runner = load_network(path, name, providers=["CPUExecutionProvider"] if name == "onnx" else None)
                error = measure_parity(net, runner, contract)
            if not error <= tolerance:
                raise ExportError(
                    f"{out_dir / path.name}: {name} export differs from eager by {error:.3g} m (> {tolerance:g} m); "
                    "not kept"
                )
            metadata["files"][name] = {"path": path.name, "sha256": sha256_file(path)}
            metadata["parity_max_abs_m"][name] = error
        if "onnx" in formats:
            metadata["onnx_opset"] = onnx_opset(build / FILE_NAMES["onnx"])
        if int8_pairs is not None:
            metadata["int8"] = quantised(build, out_dir, *int8_pairs)
            metadata["files"][INT8] = {"path": INT8_FILE_NAME, "sha256": sha256_file(build / INT8_FILE_NAME)}
        write_metadata(build, metadata)
    return metadata


def quantised(build: Path, out_dir: Path, calibration: list, check: list) -> dict:
    """Write the int8 network of ``build``'s ONNX file beside it, calibrated on ``calibration``, and return its
    difference from the float32 network on ``check`` (``fastflow3d.artifact.quantize``); refused (ExportError)
    beyond ``INT8_TOLERANCE``."""
    write_int8(build / FILE_NAMES["onnx"], build / INT8_FILE_NAME, calibration)
    float_network, int8_network = (
        load_network(build / name, "onnx", runtime="onnxruntime") for name in (FILE_NAMES["onnx"], INT8_FILE_NAME)
    )
    difference = int8_difference(float_network, int8_network, check)
    if not difference["mean_abs_m"] <= INT8_TOLERANCE:
        raise ExportError(
            f"{out_dir / INT8_FILE_NAME}: the int8 network differs from the float32 one by "
            f"{difference['mean_abs_m']:.3g} m on average (> {INT8_TOLERANCE:g} m); not kept"
        )
    return {**difference, "calibration_pairs": len(calibration), "held_out": check is not calibration}


def check_replaceable(out_dir: Path) -> None:
    """``out_dir`` is absent, empty or an export folder (only export files): an export replaces it whole, so a
    folder holding anything else (a typo such as ``out_dir=.``) is refused."""
    if not out_dir.exists():
        return
    if not out_dir.is_dir():
        raise ExportError(f"{out_dir}: exists and is not a folder; give a new or export folder as out_dir")
    ours = {METADATA_NAME, *FILE_NAMES.values(), INT8_FILE_NAME, *LEGACY_FILE_NAMES}
    others = sorted(child.name for child in out_dir.iterdir() if child.name not in ours)
    if others:
        raise ExportError(
            f"{out_dir}: holds other files than an export ({', '.join(others[:3])}{', ...' if len(others) > 3 else ''})"
            "; an export replaces its folder whole: give a new or export folder as out_dir"
        )


def default_export_dir(checkpoint: Path, cfg: dict) -> Path:
    """Where the run that wrote ``checkpoint`` exports: its config's ``export.dir`` taken relative to its
    ``checkpoint_dir`` from the checkpoint's folder (``<run>/checkpoints/x.ckpt`` -> ``<run>/export``, wherever the
    run now lives); for a checkpoint without those settings, ``<run>/export`` when its folder is named
    ``checkpoints``, else ``<checkpoint's folder>/export``. The run folder is ``<run>`` (the checkpoint's folder's
    parent when that folder is named ``checkpoints``, else the checkpoint's folder): stored settings that lead
    outside it are refused (``ExportError``, one line; a checkpoint from elsewhere cannot choose where its export
    replaces a folder), ``out_dir=`` is then the way to say where."""
    run = checkpoint.parent.parent if checkpoint.parent.name == "checkpoints" else checkpoint.parent
    checkpoint_dir, export_dir = cfg.get("checkpoint_dir"), (cfg.get("export") or {}).get("dir")
    if not (checkpoint_dir and export_dir):
        return run / "export"
    if not (isinstance(checkpoint_dir, str) and isinstance(export_dir, str)):
        raise ExportError(f"{checkpoint}: its stored checkpoint_dir / export.dir are not paths; give out_dir=")
    target = Path(os.path.normpath(checkpoint.parent / os.path.relpath(export_dir, checkpoint_dir)))
    inside = os.path.commonpath([os.path.abspath(target), os.path.abspath(run)]) == os.path.abspath(run)
    if not inside or os.path.abspath(target) == os.path.abspath(run):
        raise ExportError(
            f"{checkpoint}: its stored export.dir ({export_dir}) leads to {target}, outside its run folder {run}; "
            "give out_dir= to export there"
        )
    return target


def export_checkpoint(
    checkpoint: str | os.PathLike, out_dir: str | os.PathLike | None = None, formats=FORMATS, int8=False
) -> Path:
    """Export a training checkpoint (``fastflow3d.artifact.checkpoint.load_student``) to ``out_dir`` (default:
    :func:`default_export_dir`). ``int8``: also the int8 network (:func:`export_model`), calibrated on labelled shards:
    ``True`` those the run trained on (its config's ``data.train``: most runs validate on a few pairs only), or a
    ``label.py`` out_dir. Returns the export directory."""
    checkpoint = Path(checkpoint).expanduser()  # ~ as in every path option
    if (refused := not_a_file(checkpoint)) is not None:
        raise ExportError(refused)
    if not checkpoint.is_file():
        raise ExportError(f"{checkpoint}: checkpoint not found")
    model, cfg = load_student(checkpoint, map_location="cpu")
    try:
        contract = upgrade(cfg, grid=model.grid)
    except ContractError as error:
        raise ExportError(f"{checkpoint}: {one_line(error)}") from None
    out_dir = default_export_dir(checkpoint, cfg) if out_dir is None else Path(out_dir).expanduser()
    int8_pairs = None
    if int8 is not False and int8 is not None:
        shards = (cfg.get("data") or {}).get("train") if int8 is True else int8
        if not isinstance(shards, str | os.PathLike) or not Path(shards).is_dir():
            raise ExportError(
                f"{checkpoint}: int8 calibration needs labelled shards: {shards!r} is not a folder; "
                "give int8=<a label.py out_dir>"
            )
        int8_pairs = calibration_pairs(shards, contract)
    export_model(
        model,
        out_dir,
        formats,
        model_config=dict(cfg.get("model") or {}),
        checkpoint=checkpoint,
        contract=contract,
        int8_pairs=int8_pairs,
    )
    return out_dir


def parse_formats(value: str) -> tuple[str, ...]:
    """``onnx``, ``pt2``, ``all`` or a comma-separated list -> format names."""
    names = [part.strip() for part in str(value).split(",") if part.strip()]
    return FORMATS if names == ["all"] else tuple(names)


#: errors whose message is the line ``export.py`` prints (``icpflow.core.errors_and_signals.reported``)
EXPECTED = (ValueError, RuntimeError)


def run_export(cfg) -> int:
    """``export.py``: export ``cfg.checkpoint`` in ``cfg.format`` to ``cfg.out_dir``; print what was written.

    Returns the exit status (``icpflow.core.errors_and_signals.exit_status``, the report every entry point makes): 0
    exported, 2 could not export (one line on stderr: the file, the cause, the fix), 143 / 130 on SIGTERM / SIGINT (the
    line says that the existing export is unchanged).
    """
    return exit_status("export", lambda: _run_export(cfg), *EXPECTED)


def _run_export(cfg) -> None:
    from omegaconf import OmegaConf

    if OmegaConf.is_missing(cfg, "checkpoint") or not cfg.checkpoint:
        raise ExportError("pass checkpoint=<path to a training .ckpt>")
    formats = parse_formats(cfg.format)
    if Path(cfg.checkpoint).is_file() and formats and set(formats) <= set(FORMATS):  # a long step: say so
        print(f"export: exporting {cfg.checkpoint}, then checking parity (about 20 s) ...", file=sys.stderr)
    try:
        with stop_on_signals():
            out_dir = export_checkpoint(cfg.checkpoint, cfg.out_dir, formats, cfg.int8)
    except Stop as stop:
        where = cfg.out_dir or "the export folder"
        raise Stop(stop.signum, f"{signal_words(stop.signum)}; nothing exported, {where} is as it was") from None
    except OSError as error:
        raise ExportError(f"{os_error_line(error)}; the export there is as it was") from None
    metadata = json.loads((out_dir / METADATA_NAME).read_text())
    for name, entry in metadata["files"].items():
        if name == INT8:
            int8 = metadata["int8"]
            print(
                f"export: {name} -> {out_dir / entry['path']} (|int8 - float32| mean {int8['mean_abs_m']:.2e} m, "
                f"max {int8['max_abs_m']:.2e} m on {int8['pairs']} labelled pairs)"
            )
            continue
        print(
            f"export: {name} -> {out_dir / entry['path']} (max |export - eager| "
            f"{metadata['parity_max_abs_m'][name]:.2e} m)"
        )
    print(f"export: metadata -> {out_dir / METADATA_NAME}")
