"""How a Predictor opens its model (``Predictor.load``): an export directory, one exported file or a training
checkpoint, opened in its engine by ``fastflow3d.artifact.engines.load_network``, with the metadata that describes it;
and the input contract the model was trained with (``fastflow3d.network.contract``: saved in its metadata or
checkpoint, or given for a bare exported file)."""

from __future__ import annotations

import json
import os
from pathlib import Path

from fastflow3d.artifact.engines import (
    PRECISION_RUNTIMES,
    PRECISIONS,
    RUNTIMES,
    choose_format,
    cpu_only,
    int8_dot_products,
    load_network,
)
from fastflow3d.artifact.file_format import (
    FORMATS,
    INT8,
    LEGACY_FORMATS,
    METADATA_NAME,
    SUFFIX_FORMATS,
    ArtifactError,
    listed_file,
    network_metadata,
    read_metadata,
    sibling_metadata,
)
from fastflow3d.artifact.safe_loading import TORCHSCRIPT_WARNING
from fastflow3d.inference.prediction import PredictorError
from fastflow3d.network.contract import ContractError, InputContract, read_grid, upgrade
from icpflow.core.errors_and_signals import one_line
from icpflow.core.files import NotAFile, not_a_file, read_text

#: the precision the CLI, ``eval.py`` and ``Predictor.load`` run a student in unless told: :func:`auto_precision`
AUTO = "auto"
#: the precisions a student runs in when asked by name (``fastflow3d-infer --precision``, ``Predictor.load``)
PRECISION_CHOICES = (AUTO, *PRECISIONS)


def check_precision(precision) -> None:
    """Refuse a precision that is not one of :data:`PRECISION_CHOICES` (``"INT8"``, ``"fp32"``, None, 8 ran float32
    silently before) in one line naming them."""
    if not (isinstance(precision, str) and precision in PRECISION_CHOICES):
        raise PredictorError(f"precision={precision!r}: use one of {', '.join(PRECISION_CHOICES)}")


def check_load_options(precision, sensor_height, threads, device, runtime) -> None:
    """What ``Predictor.load``, ``fastflow3d-infer`` and ``eval.py`` refuse alike, before a model is opened, each in
    one line (:class:`PredictorError`): a precision not in :data:`PRECISION_CHOICES`, a sensor height that is not
    None, ``auto`` or metres (``scan_steps.check_sensor_height``), threads that are not a whole number >= 1 (None:
    the usable cores), a device torch cannot name or does not have, a runtime not in ``engines.RUNTIMES``."""
    from fastflow3d.inference.scan_steps import check_sensor_height

    check_precision(precision)
    check_sensor_height(sensor_height)
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
        raise PredictorError(f"threads={threads!r} must be a whole number >= 1 (or None: the usable cores)")
    if runtime is not None and runtime not in RUNTIMES:
        raise PredictorError(f"runtime={runtime!r}: use one of {', '.join(RUNTIMES)} (or None: ONNX Runtime)")
    check_device(device)


def check_device(device) -> None:
    """Refuse a torch device that torch cannot parse (``gpu``) or that this machine does not have (``cuda:9``)."""
    import torch

    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError) as error:
        raise PredictorError(f"device={device!r}: not a torch device ({one_line(error)}); e.g. cpu or cuda:0") from None
    if parsed.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if (parsed.index or 0) >= count:
            raise PredictorError(f"device={device!r}: torch sees {count} CUDA device(s) here; use cpu")


def auto_precision(path: Path, backend: str | None, runtime: str | None) -> str:
    """The precision ``auto`` runs the model at ``path`` in (``Predictor.load``'s arguments): ``int8`` where the
    export ships its int8 network (checked against the float32 one when it was written:
    ``fastflow3d.artifact.quantize``), ONNX Runtime runs it on the CPU and the CPU has int8 dot products
    (``fastflow3d.artifact.engines.int8_dot_products``: there its convolutions take half the float32 ones' time, and
    the stream's frame 0.7x: BENCHMARKS.md, "Student latency and the stream"); a bare int8 ``.onnx`` of an export,
    int8 (it runs no other way); else ``f32``: a checkpoint, another format or runtime, ONNX Runtime with its CUDA
    provider, a CPU without them."""
    if backend not in (None, "onnx") or runtime not in (None, "onnxruntime"):
        return "f32"
    if path.suffix.lower() == ".onnx" and path.is_file():
        return "int8" if sibling_metadata(path, INT8) else "f32"
    if not path.is_dir():
        return "f32"
    try:
        shipped = INT8 in read_metadata(path / METADATA_NAME)["files"]
    except ArtifactError:
        return "f32"  # opening it says what is wrong
    # without a runtime named, ONNX Runtime runs on its CUDA provider where it has one
    return "int8" if shipped and int8_dot_products() and (runtime is not None or cpu_only()) else "f32"


def precision_cost(precision: str) -> str | None:
    """One line on what a reduced ``precision`` asked for by name costs on this CPU, where it is not native (None
    where it is, and for f32): int8 without int8 dot products (``engines.int8_dot_products``), bf16 without native
    bf16 (``icpflow.core.hardware.native_bf16``)."""
    from icpflow.core.hardware import native_bf16

    if precision == "int8" and not int8_dot_products():
        return (
            "precision int8 on a CPU without int8 dot products (VNNI, Arm dot product): ONNX Runtime multiplies "
            "with 16-bit sums that can saturate, so the export's check of the int8 network does not hold here, and "
            "it is no quicker than f32 (--precision auto runs f32 here)"
        )
    if precision == "bf16":
        native, why = native_bf16()
        if not native:
            return f"precision bf16: {why}; OpenVINO runs float32 instead (--precision auto runs f32 here)"
    return None


def open_model(
    path: Path, backend: str | None, device: str, runtime: str | None, threads: int | None, precision: str
) -> tuple[object, str, dict, str]:
    """``(network, backend, metadata, precision)`` of the model at ``path`` (``Predictor.load``'s arguments): the
    network numpy in, numpy out; the backend it runs in (a format, ``eager`` for a checkpoint, or the ONNX
    ``runtime``); the metadata that describes it ({} for a bare exported file without its ``metadata.json``); the
    precision it runs in (``auto`` resolved by :func:`auto_precision`). A ``precision`` other than ``f32`` picks its
    runtime when none is given (``bf16``: openvino; ``int8``: onnxruntime, on the export's int8 file)."""
    if precision == AUTO:
        precision = auto_precision(path, backend, runtime)
    runtime = runtime or PRECISION_RUNTIMES.get(precision)
    if runtime is not None:
        entry = INT8 if precision == "int8" else "onnx"
        if path.is_dir():
            metadata = read_metadata(path / METADATA_NAME)
            if entry not in metadata["files"] and entry == INT8:
                raise PredictorError(
                    f"{path}: the export has no int8 network; export it with export.py checkpoint=<.ckpt> int8=true"
                )
            file = listed_file(path, metadata, entry)
        elif path.suffix.lower() == ".onnx" and path.is_file():
            file, metadata = path, sibling_metadata(path, entry)
        else:
            raise PredictorError(f"{path}: runtime {runtime!r} needs an export directory with ONNX or a .onnx")
        network = load_network(file, "onnx", runtime=runtime, threads=threads, precision=precision)
        kind = runtime
    elif path.is_dir():
        metadata = read_metadata(path / METADATA_NAME)
        kind = backend or choose_format(metadata["files"], path)
        if kind not in FORMATS + LEGACY_FORMATS:
            raise PredictorError(f"{path}: unknown backend {kind!r}; use one of {', '.join(FORMATS)}")
        network = load_network(listed_file(path, metadata, kind), kind, device, threads=threads)
    else:
        kind = "checkpoint" if path.suffix.lower() == ".ckpt" else SUFFIX_FORMATS.get(path.suffix.lower())
        if kind is None:
            raise PredictorError(f"{path}: expected an export directory, .onnx, .pt2, .pt (TorchScript) or .ckpt")
        if (refused := not_a_file(path)) is not None:
            raise PredictorError(refused)
        if not path.is_file():
            raise PredictorError(f"{path}: file not found")
        if backend is not None and backend != kind:
            raise PredictorError(f"{path}: a {path.suffix} file cannot run with backend {backend!r}")
        if kind in LEGACY_FORMATS and backend is None:
            raise PredictorError(f"{path}: refused: {TORCHSCRIPT_WARNING}")
        if kind == "checkpoint":
            network, kind = load_network(path, "checkpoint", device), "eager"
            model, cfg = network.module.model, network.config
            contract = checkpoint_contract(path, cfg, model.grid)
            metadata = network_metadata(model, dict(cfg.get("model") or {}), path, contract)
        else:
            metadata = sibling_metadata(path, kind)
            if not metadata and kind == "onnx" and sibling_metadata(path, INT8):
                raise PredictorError(
                    f"{path}: this is its export's int8 network; run it with precision 'int8' or 'auto' "
                    "(the defaults of fastflow3d-infer --precision and eval.py precision=)"
                )
            network = load_network(path, kind, device, threads=threads)
    return network, kind, metadata, precision


def model_contract(path: Path, metadata: dict, preprocessing) -> InputContract:
    """The input contract of the model at ``path``: ``preprocessing`` where given (:func:`given_contract`), else the
    one its ``metadata`` stores; a bare exported file with neither is refused (one line saying what to pass)."""
    if not metadata and preprocessing is None:
        raise PredictorError(
            f"{path}: no {METADATA_NAME} beside it describes this file, so its preprocessing (ground "
            "removal, height frame) is unknown and running it could silently give wrong flow; load its "
            "export directory, or pass what the metadata says: preprocessing=<metadata.json> "
            "(fastflow3d-infer --metadata FILE), or {'remove_ground': False} (--remove-ground no) to run "
            "it on every point"
        )
    if preprocessing is not None:
        grid = metadata.get("grid") if isinstance(metadata, dict) else None
        contract = given_contract(preprocessing, read_grid(grid, path) if isinstance(grid, dict) else None)
    else:
        try:
            contract = upgrade(metadata)
        except ContractError as error:
            raise PredictorError(f"{path}: metadata: {one_line(error)}") from None
    return contract


def checkpoint_contract(path: Path, cfg: dict, grid) -> InputContract:
    """The input contract a checkpoint's saved config stores (any version), one line naming it if unreadable."""
    try:
        return upgrade(cfg, grid=grid)
    except ContractError as error:
        raise PredictorError(f"{path}: {one_line(error)}") from None


def given_contract(given, grid) -> InputContract:
    """The input contract a user passes for a bare exported file (``Predictor.load(preprocessing=...)``): a
    ``metadata.json`` path or dict, its ``input`` / ``preprocessing`` entry, or ``{"remove_ground": ...}``; the
    model's ``grid`` (a Grid, or None when unknown) where the given form has none."""
    if isinstance(given, (str, os.PathLike)):
        try:
            given = json.loads(read_text(given))
        except NotAFile as error:  # a FIFO, a device, a file too large: its own line
            raise PredictorError(str(error)) from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
            raise PredictorError(f"{given}: cannot read preprocessing: {one_line(error)}") from None
    if not isinstance(given, dict):
        raise PredictorError(f"preprocessing must be a dict or a JSON file, got {type(given).__name__}")
    try:
        contract = upgrade(given)
    except ContractError as error:
        raise PredictorError(f"preprocessing: {one_line(error)}") from None
    return contract if contract.grid is not None else contract.replace(grid=grid)
