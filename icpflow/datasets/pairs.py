"""Your own frame pairs: a directory of ``.npz`` files, one pair each, already in the project's conventions.

Files: ``<root>/<split>/*.npz`` if that folder exists, else ``<root>/*.npz`` (sorted by name). Keys:

* required ``pc0`` (N0, 3), ``pc1`` (N1, 3): metres, each scan in its own ego frame (more columns are allowed: the
  first three are x, y, z; see ``icpflow.core.frame_pair.check_points``);
* optional ``ego1_from_ego0`` (4, 4), or ``pose0`` and ``pose1`` (4, 4, world_from_ego) -- without either the
  teacher estimates ego motion; ``eval.py`` needs it to score ground truth (the splits are by motion beyond the
  ego's), and says so for each such pair;
* optional ``ground0`` (N0,), ``ground1`` (N1,) bool;
* optional ground truth for pc0: ``flow`` (N0, 3) FULL flow (``pc0 + flow`` in pc1's frame), ``flow_valid``,
  ``dynamic`` (N0,) bool, ``classes``, ``instance`` (N0,) integers with 0 = background;
* optional ``dt`` (seconds, default 0.1).

Arrays are cast to the schema's dtypes (float32 points and flow, float64 transforms, bool masks, int32 labels);
any other problem (missing key, wrong shape, NaN rows, empty scan, damaged file) is a one-line error naming it.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from icpflow.core.frame_pair import FramePair, check_points
from icpflow.datasets.base import IndexedDataset
from icpflow.datasets.file_formats import fail, load_npz

TRANSFORMS = ("ego1_from_ego0", "pose0", "pose1")
MASKS = ("ground0", "ground1", "flow_valid", "dynamic")
LABELS = ("classes", "instance")
KNOWN = ("pc0", "pc1", "flow", "dt", *TRANSFORMS, *MASKS, *LABELS)


class NpzPairsDataset(IndexedDataset):
    """One frame pair per ``.npz`` file (see the module docstring for the keys)."""

    name = "pairs"

    def __init__(self, root: str | Path, split: str | None = None) -> None:
        self.root = Path(root)
        self.split = split
        folder = self.root / split if split and (self.root / split).is_dir() else self.root
        self._index_files(sorted(folder.glob("*.npz")))
        self._said_unknown = False
        if not self.files:
            raise fail(folder, "no .npz pair files")

    def metadata(self) -> dict:
        return {**super().metadata(), "root": str(self.root), "split": self.split}

    def pair(self, index: int, horizon: int = 1) -> FramePair:
        if horizon != 1:
            raise IndexError(f"{self.name}: a pair file holds horizon 1 only, got {horizon}")
        path = self.files[index]
        data = load_npz(path, ("pc0", "pc1"), optional=KNOWN)  # other keys are never read (nor unpickled)
        with np.load(path, allow_pickle=False) as archive:  # their names only
            unknown = sorted(set(archive.files) - set(KNOWN))
        if unknown and not self._said_unknown:  # a misspelt field would be lost silently otherwise; said once
            self._said_unknown = True
            warnings.warn(
                f"{path}: key(s) {', '.join(unknown)} are no pair field and are ignored (known: {', '.join(KNOWN)})",
                UserWarning,
                stacklevel=2,
            )
        fields = {}
        for name in ("pc0", "pc1"):
            fields[name] = check_points(data[name], path, name, allow_empty=False)
        if "flow" in data:
            fields["flow"] = np.asarray(data["flow"], np.float32)
        for name in TRANSFORMS:
            if name in data:
                fields[name] = np.asarray(data[name], np.float64)
        for name in MASKS:
            if name in data:
                fields[name] = self._cast(path, name, data[name], np.bool_)
        for name in LABELS:
            if name in data:
                fields[name] = self._cast(path, name, data[name], np.int32)
        if "dt" in data:
            fields["dt"] = float(np.asarray(data["dt"]).reshape(-1)[0]) if data["dt"].size == 1 else np.nan
        return FramePair(**fields, sample_id=self.sample_id(index), source=str(path))

    @staticmethod
    def _cast(path, name: str, values: np.ndarray, dtype) -> np.ndarray:
        """Integer or bool arrays to ``dtype``; floats are refused, they would round silently."""
        if not (values.dtype == np.bool_ or np.issubdtype(values.dtype, np.integer)):
            raise fail(path, f"{name} must hold integers or booleans, got {values.dtype}")
        return values.astype(dtype)
