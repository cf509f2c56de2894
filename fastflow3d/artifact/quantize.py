"""The int8 network of an export (``fastflow3d.int8.onnx``): ONNX Runtime's static quantisation of the exported ONNX,
calibrated on the network's own inputs from labelled shards.

Only the convolutions are quantised (QDQ: int8 weights per output channel, uint8 activations with min-max ranges);
the pillar encoder's scatters, the cost volume, the decoder and the heads stay float32. On a CPU with VNNI
(AVX512-VNNI, AVX-VNNI) ONNX Runtime runs these convolutions in int8, about half the network's time
(BENCHMARKS.md, "Student latency and the stream" and "Every CPU"). Min-max ranges, not percentiles: clipping the
activations' largest values clips the largest flows (dynamic-foreground EPE +30 % on the 64 test pairs;
docs/history.md, "Int8 convolutions (point 3)").

The calibration pairs are what the network sees in use (``fastflow3d.network.contract.InputContract.prepare``: pc0
compensated, the ground dropped where the contract removes it, cropped to the grid) from the shards' scans, ego motion
and ground masks (``icpflow.shards.reader.ShardDataset``). The int8 network is then compared with the float32 one on
other pairs of the same shards (the calibration pairs where the shards hold no others): the mean and largest
difference of the residual over the valid points are written to the export's metadata (``int8``), and an int8 network
whose mean difference exceeds :data:`INT8_TOLERANCE` is refused.
"""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path

import numpy as np

from fastflow3d.artifact.file_format import INPUT_NAMES, ArtifactError
from fastflow3d.network.contract import InputContract
from icpflow.core.atomic import atomic_path
from icpflow.core.errors_and_signals import one_line
from icpflow.shards.reader import ShardDataset

#: labelled pairs the activation ranges are measured on, and at most as many others the int8 network is checked on
CALIBRATION_PAIRS = 32
#: metres: the largest mean |int8 - float32| residual difference (valid points of the check pairs) an export keeps
INT8_TOLERANCE = 0.05


def calibration_pairs(shard_dir, contract: InputContract, count: int = CALIBRATION_PAIRS):
    """``(calibration, check)``: two lists of network inputs ``(pc0_compensated (K0, 3), pc1 (K1, 3))`` float32 from
    the labelled shards of ``shard_dir`` (a ``label.py`` out_dir), as ``contract`` prepares them: up to ``count``
    pairs spread over the shards for the ranges and up to ``count`` others between them for the check (the
    calibration pairs again where the shards hold no others). Pairs with no point in the grid are passed over.
    Unreadable or empty shards raise :class:`~fastflow3d.artifact.file_format.ArtifactError` (one line)."""
    try:
        shards = ShardDataset(shard_dir)
    except (FileNotFoundError, ValueError) as error:
        raise ArtifactError(f"int8 calibration: {one_line(error)}") from None
    if len(shards) == 0:
        raise ArtifactError(f"{shard_dir}: int8 calibration: the shards hold no samples")
    picks = np.unique(np.linspace(0, len(shards) - 1, min(2 * count, len(shards))).round().astype(int))
    inputs = []
    for index in picks:
        try:
            sample = shards[int(index)]
        except (OSError, ValueError, KeyError) as error:
            raise ArtifactError(f"{shard_dir}: int8 calibration: sample {index}: {one_line(error)}") from None
        pair = contract.prepare(
            sample["pc0"], sample["pc1"], sample["ego1_from_ego0"], sample["ground0"], sample["ground1"]
        )
        if len(pair.network0) and len(pair.network1):
            inputs.append((pair.network0, pair.network1))
    if not inputs:
        raise ArtifactError(f"{shard_dir}: int8 calibration: no labelled pair has points in the network's grid")
    calibration, check = inputs[::2], inputs[1::2]
    return calibration, check or calibration


def write_int8(onnx_file: Path, int8_file: Path, calibration) -> None:
    """Write the int8 network of the float32 ONNX ``onnx_file`` to ``int8_file`` (atomically), its activation ranges
    measured on the ``calibration`` network inputs (:func:`calibration_pairs`)."""
    from onnxruntime.quantization import (
        CalibrationDataReader,
        CalibrationMethod,
        QuantFormat,
        QuantType,
        quantize_static,
    )
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class Feed(CalibrationDataReader):
        """ONNX Runtime's calibration reader over the list of network inputs."""

        def __init__(self, pairs):
            self.pairs = iter(pairs)

        def get_next(self):
            pair = next(self.pairs, None)
            return None if pair is None else dict(zip(INPUT_NAMES, pair))

    with tempfile.TemporaryDirectory(prefix="int8-", dir=int8_file.parent) as work, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the quantiser's deprecation and shape-inference notes
        prepared = Path(work) / "prepared.onnx"
        quant_pre_process(str(onnx_file), str(prepared), skip_symbolic_shape=True)
        with atomic_path(int8_file) as tmp:
            quantize_static(
                str(prepared),
                str(tmp),
                Feed(calibration),
                quant_format=QuantFormat.QDQ,
                per_channel=True,
                activation_type=QuantType.QUInt8,
                weight_type=QuantType.QInt8,
                op_types_to_quantize=["Conv"],
                calibrate_method=CalibrationMethod.MinMax,
            )


def int8_difference(float_network, int8_network, pairs) -> dict:
    """``{"mean_abs_m", "max_abs_m", "pairs"}``: the mean and largest Euclidean difference (m) of the two networks'
    residuals over the points both call valid, on ``pairs`` (network inputs); runners take and give numpy."""
    total, count, worst = 0.0, 0, 0.0
    for pc0, pc1 in pairs:
        residual, valid = float_network(pc0, pc1)
        quantised, valid8 = int8_network(pc0, pc1)
        both = np.asarray(valid, bool) & np.asarray(valid8, bool)
        distance = np.linalg.norm(np.asarray(quantised) - np.asarray(residual), axis=1)[both]
        if not np.isfinite(distance).all():
            raise ArtifactError("the int8 network gives non-finite flow")
        total, count = total + float(distance.sum()), count + len(distance)
        worst = max(worst, float(distance.max(initial=0.0)))
    return {"mean_abs_m": total / max(count, 1), "max_abs_m": worst, "pairs": len(pairs)}
