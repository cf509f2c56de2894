"""Deprecated, removed in 0.3: the last release's ``fastflow3d.model``, today ``fastflow3d.network.model``
(``pillar_rows``: ``fastflow3d.network.cells.image_rows``). Old checkpoints name ``fastflow3d.model.FastFlow3D``:
``fastflow3d.artifact.checkpoint.read_checkpoint`` reads it as today's path, without this module."""

from fastflow3d.network.cells import image_rows as pillar_rows
from fastflow3d.network.model import (
    DECODERS,
    NORMS,
    ConvNormAct,
    FastFlow3D,
    GRUDecoder,
    LinearDecoder,
    PillarEmbedder,
    UNet,
    UpsampleSkip,
    compensate,
    encoder_stage,
    local_correlation,
    norm_layer,
    split_linear,
)
from icpflow.core.deprecation import warn_moved

__all__ = [
    "DECODERS",
    "NORMS",
    "ConvNormAct",
    "FastFlow3D",
    "GRUDecoder",
    "LinearDecoder",
    "PillarEmbedder",
    "UNet",
    "UpsampleSkip",
    "compensate",
    "encoder_stage",
    "local_correlation",
    "norm_layer",
    "pillar_rows",
    "split_linear",
]

warn_moved("fastflow3d.model", "fastflow3d.network.model")
