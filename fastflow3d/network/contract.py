"""The student's input contract: what the network sees, and how a pair of scans becomes that and back.

"The network gets the points of each scan inside its grid (and, with ``remove_ground``, off the ground), in the
model's height frame, with pc0 moved by the ego motion into the ego frame of t + dt" is written here once, as
:class:`InputContract`:

- ``preprocessing`` (``icpflow.scans.preprocess.Preprocessing``): the height frame (``frame.ground_z``: where the ground
  sits in the frame the network saw), the teacher's ground settings (Patchwork++'s z offset follows from the frame
  and the sensor height, never stored) and its ego-motion settings;
- ``remove_ground``: the network sees only the non-ground points of each scan (ZeroFlow's input);
- ``grid`` (``fastflow3d.network.voxelize.Grid``): the pillar grid; a point outside it is not the network's (None:
  unknown, for a bare exported file without its metadata: every point goes in and the network's own validity decides).

:meth:`InputContract.prepare` turns a pair into the network's input (lift into the height frame, compensate pc0,
drop ground, crop to the grid) and :meth:`InputContract.restore` puts the network's residual back on the input rows;
:meth:`InputContract.network_mask` is the row test itself, for a flat batch of points (training, validation).
Training (``fastflow3d.training.data.NetworkCrop``), validation (``StudentModule.forward``), the ``Predictor`` and the
export's parity check all call them.

Stored form (:meth:`InputContract.to_dict`, version :data:`VERSION`): ``input`` of a checkpoint's saved config and
of an export's ``metadata.json``. The shards hold the teacher's part only (``preprocessing`` of the labeller YAML,
written by ``icpflow``, which knows no student grid); the training run adds ``remove_ground`` and the grid.
:func:`upgrade` reads every stored form, this version's and each older one, into a contract; it is the only reader.

Shapes and frames: points (N, 3) float32 metres; transforms (4, 4) float64 ``b_from_a``; masks (N,) bool.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
import torch

from fastflow3d.network.model import compensate
from fastflow3d.network.voxelize import Grid, in_grid
from icpflow.core.errors_and_signals import one_line
from icpflow.scans.preprocess import VERSION as PREPROCESSING_VERSION
from icpflow.scans.preprocess import Preprocessing, PreprocessingError, lift_points, lift_transform

#: version of the stored form; 1 was the export metadata's ``preprocessing`` entry (``Preprocessing.to_dict()`` plus
#: ``remove_ground``) and a checkpoint's ``data.preprocessing`` beside ``data.remove_ground``; before it, flat
#: teacher fields (``teacher`` of an export's entry, ``data.teacher`` of a checkpoint)
VERSION = 2


class ContractError(ValueError):
    """A stored input contract that cannot be read (one line, naming the field)."""


@dataclass(frozen=True)
class PreparedPair:
    """A pair as the network takes it. ``pc0`` / ``pc1`` (N0, 3) / (N1, 3): the scans in the height frame;
    ``ego1_from_ego0`` (4, 4) in that frame; ``compensated`` (N0, 3): pc0 moved into the ego frame of t + dt;
    ``ground0`` / ``ground1``: the masks left out (all False unless ``remove_ground``); ``inside0`` (N0,) bool:
    ``compensated`` inside the grid, ground or not; ``rows0`` / ``rows1`` (K0,) / (K1,) int64: the input rows the
    network sees (in the grid, off the ground); ``network0`` / ``network1``
    (K0, 3) / (K1, 3) float32 C-contiguous: those rows of ``compensated`` and ``pc1``."""

    pc0: np.ndarray
    pc1: np.ndarray
    ego1_from_ego0: np.ndarray
    compensated: np.ndarray
    ground0: np.ndarray
    ground1: np.ndarray
    inside0: np.ndarray
    rows0: np.ndarray
    rows1: np.ndarray

    @property
    def network0(self) -> np.ndarray:
        return np.ascontiguousarray(self.compensated[self.rows0])

    @property
    def network1(self) -> np.ndarray:
        return np.ascontiguousarray(self.pc1[self.rows1])


@dataclass(frozen=True)
class InputContract:
    """What the network sees (module docstring). ``InputContract()`` is the synthetic world's with ground removal
    and FastFlow3D's default grid."""

    preprocessing: Preprocessing = field(default_factory=Preprocessing)
    remove_ground: bool = True
    grid: Grid | None = field(default_factory=Grid)

    # ------------------------------------------------------------------------------------------------ rows
    def network_mask(self, points, ground=None):
        """(N,) bool: the rows of (N, 3) ``points`` (pc1, or pc0 already compensated; numpy or torch, any number of
        samples concatenated) that the network sees: inside the grid (``fastflow3d.network.voxelize.in_grid``, the
        network's own test) and, with ``remove_ground``, not in the (N,) bool ``ground``. Same type as ``points``."""
        as_numpy = isinstance(points, np.ndarray)
        tensor = torch.from_numpy(points) if as_numpy else points
        if self.grid is None:
            inside = torch.ones(len(tensor), dtype=torch.bool, device=tensor.device)
        else:
            inside = in_grid(tensor, self.grid)
        if self.remove_ground and ground is not None:
            inside &= ~(torch.from_numpy(np.asarray(ground, bool)) if as_numpy else ground)
        return inside.numpy() if as_numpy else inside

    @staticmethod
    def lifted(pc0: np.ndarray, pc1: np.ndarray, lift: float) -> tuple[np.ndarray, np.ndarray]:
        """Both (N, 3) scans raised by ``lift`` m into the height frame (the same arrays when ``lift`` is 0)."""
        return lift_points(pc0, lift), lift_points(pc1, lift)

    def prepare(self, pc0, pc1, ego1_from_ego0, ground0, ground1, lift: float = 0.0) -> PreparedPair:
        """The pair (N0, 3) / (N1, 3) float32 in the scans' own frame, ``ego1_from_ego0`` (4, 4) in that frame and
        the (N,) bool ground masks (ignored, all False, unless ``remove_ground``), as the network takes it: both
        scans raised by ``lift`` m into the height frame, pc0 compensated, ground dropped, cropped to the grid."""
        pc0_frame, pc1_frame = self.lifted(pc0, pc1, lift)
        ego = lift_transform(np.asarray(ego1_from_ego0, np.float64), lift) if lift else np.asarray(ego1_from_ego0)
        if not self.remove_ground:
            ground0, ground1 = np.zeros(len(pc0), bool), np.zeros(len(pc1), bool)
        compensated = compensate(pc0_frame, ego)
        inside0 = self.network_mask(compensated)  # the grid's test alone, once: the rows and the plausibility check
        rows0 = np.flatnonzero(inside0 & ~ground0)
        rows1 = np.flatnonzero(self.network_mask(pc1_frame, ground1))
        return PreparedPair(pc0_frame, pc1_frame, ego, compensated, ground0, ground1, inside0, rows0, rows1)

    @staticmethod
    def restore(prepared: PreparedPair, residual: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The network's (K0, 3) residual and (K0,) validity on ``prepared.rows0`` put back on pc0's rows: (N0, 3)
        float32 residual (0 where the network did not predict) and (N0,) bool ``in_grid``."""
        count = len(prepared.pc0)
        full, in_grid = np.zeros((count, 3), np.float32), np.zeros(count, bool)
        valid = np.asarray(valid, bool)
        in_grid[prepared.rows0] = valid
        full[prepared.rows0] = np.where(valid[:, None], residual, 0.0)
        return full, in_grid

    # ------------------------------------------------------------------------------------------------ stored form
    def to_dict(self) -> dict:
        """The stored form: ``version``, ``frame``, ``ground`` (without the derived Patchwork++ offset),
        ``ego_motion``, ``remove_ground``, ``grid`` (ranges and cell in metres), plain JSON / YAML values."""
        grid = None
        if self.grid is not None:
            grid = {key: list(value) if isinstance(value, tuple) else value for key, value in vars(self.grid).items()}
        stored = self.preprocessing.to_dict()
        return {**stored, "version": VERSION, "remove_ground": bool(self.remove_ground), "grid": grid}

    def replace(self, **changes) -> InputContract:
        return dataclasses.replace(self, **changes)


def read_grid(values, where: str) -> Grid:
    """The ``Grid`` of a stored ``grid`` mapping (ranges, cell; other keys such as ``nx`` are ignored)."""
    if not isinstance(values, dict):
        raise ContractError(f"{where}: grid must be a mapping, got {type(values).__name__}")
    try:
        return Grid(
            **{
                key: tuple(value) if isinstance(value, list) else value
                for key, value in values.items()
                if key in ("x_range", "y_range", "z_range", "cell")
            }
        )
    except (TypeError, ValueError) as error:
        raise ContractError(f"{where}: grid: {one_line(error)}") from None


def _preprocessing(block, where: str) -> Preprocessing:
    try:
        return Preprocessing.from_dict(block)
    except (PreprocessingError, ValueError, TypeError) as error:
        raise ContractError(f"{where}: {one_line(error)}") from None


def upgrade(stored, *, remove_ground: bool | None = None, grid: Grid | None = None) -> InputContract:
    """The :class:`InputContract` of any stored form (the only reader of them):

    - this version's :meth:`~InputContract.to_dict`, or a dict holding it as ``input`` (an export's metadata, a
      checkpoint's saved config);
    - an export's metadata of an older version: its ``preprocessing`` entry (``remove_ground`` plus the typed block
      of version 1, or plus flat ``teacher`` fields before it; none at all: every point, the synthetic frame) and
      its ``grid``;
    - a checkpoint's saved config of an older version: ``data.preprocessing`` (version 1) or ``data.teacher``
      (flat fields) beside ``data.remove_ground`` (no ``data``: every point), and the grid of ``model``;
    - the teacher's block alone (``preprocessing`` of a shard's labeller YAML, or its flat ``teacher`` fields, or
      the labeller YAML itself): ``remove_ground`` and ``grid`` must then be given (the training run's).

    ``remove_ground`` / ``grid`` given here replace stored ones (a form without a grid: None, unknown). A form
    that cannot be read raises :class:`ContractError` (one line)."""
    if not isinstance(stored, dict):
        raise ContractError(f"input contract must be a mapping, got {type(stored).__name__}")
    if "input" in stored:
        stored = stored["input"]
        if not isinstance(stored, dict):
            raise ContractError(f"input contract must be a mapping, got {type(stored).__name__}")
        if stored.get("version") != VERSION:
            raise ContractError(f"input contract version {stored.get('version')!r} is not {VERSION}; update icpflow")
    version = stored.get("version")
    if isinstance(version, int) and not isinstance(version, bool) and version > VERSION:
        raise ContractError(f"input contract version {version} is newer than this code's ({VERSION}); update icpflow")
    if version == VERSION:
        block = {**stored, "version": PREPROCESSING_VERSION}
        stored_ground, stored_grid = stored.get("remove_ground"), stored.get("grid")
    elif {"metadata_version", "files", "flow_convention"} & set(stored):  # an export's metadata of an older version
        entry = stored.get("preprocessing", {"remove_ground": False})  # none: trained on every point
        if not isinstance(entry, dict):
            raise ContractError(f"metadata: preprocessing must be a mapping, got {type(entry).__name__}")
        block = entry if "version" in entry else entry.get("teacher")
        stored_ground, stored_grid = bool(entry.get("remove_ground", False)), stored.get("grid")
    elif "model" in stored:  # a checkpoint's saved config of an older version
        data = stored.get("data") or {}  # none: trained on every point, before ground removal
        block = data["preprocessing"] if data.get("preprocessing") is not None else data.get("teacher")
        stored_ground, stored_grid = bool(data.get("remove_ground", False)), stored.get("model")
    elif "remove_ground" in stored:  # an export's preprocessing entry on its own
        block = stored if "version" in stored else stored.get("teacher")
        stored_ground, stored_grid = bool(stored["remove_ground"]), stored.get("grid")
    else:  # the teacher's part: a shard's block, flat teacher fields, or a labeller YAML holding either
        block = stored.get("preprocessing", stored.get("teacher", stored))
        stored_ground, stored_grid = None, None
    remove_ground = stored_ground if remove_ground is None else remove_ground
    if remove_ground is None:
        raise ContractError("input contract: the stored form says nothing about ground removal; give remove_ground")
    if grid is None and stored_grid is not None:
        grid = read_grid(stored_grid, "input contract")
    return InputContract(_preprocessing(block, "input contract"), bool(remove_ground), grid)
