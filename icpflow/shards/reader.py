"""Map-style dataset over all shards of a labelling run, for the student's DataLoader."""

from __future__ import annotations

import json
import os
from pathlib import Path

import h5py
import numpy as np

from icpflow.core.files import read_text
from icpflow.shards.access import ShardError, open_shard, shard_array, shard_group
from icpflow.shards.schema import OPTIONAL, REQUIRED, group_name
from icpflow.shards.verify import verify_shard


class ShardDataset:
    """Random access to every labelled sample listed in ``<out_dir>/index.json``.

    ``ds[i]`` is a dict of numpy arrays (``pc0``, ``pc1``, ``ground0``, ``ground1``, ``ego1_from_ego0``, ``flow``,
    ``confidence``, ``cluster`` and any ``gt_*`` present) plus ``sample_id``, ``log_id``, ``dt``. Files are opened
    lazily and cached per process (the cache is dropped on pickling and after a fork), so it is safe in a torch
    DataLoader with workers; each file and array through ``icpflow.shards.access`` (no read outside the label
    folder, sizes bounded before allocation: :class:`~icpflow.shards.access.ShardError` otherwise).
    """

    def __init__(self, out_dir):
        self.root = Path(out_dir)
        index_path = self.root / "index.json"
        if not index_path.is_file():
            raise FileNotFoundError(f"{index_path}: no index (run label.py first)")
        try:
            index = json.loads(read_text(index_path))
            shards = index["shards"]
            #: (file name, number of samples) of each shard, and the config hash they were labelled with
            self.shard_sizes = [(shard["file"], len(shard["samples"])) for shard in shards]
            self.config_hash = index.get("config_hash")
            self.entries = [(shard["file"], position) for shard in shards for position in range(len(shard["samples"]))]
            #: sample id of each entry, in order (from the index, without opening a shard)
            self.sample_ids = [sample["sample_id"] for shard in shards for sample in shard["samples"]]
            #: (complete, labelled, failed, planned) as label.py wrote them; None: an older index without them
            self.completeness = (
                (bool(index["complete"]), index.get("labelled"), index.get("failed"), index.get("planned"))
                if "complete" in index
                else None
            )
        except (ValueError, KeyError, TypeError) as error:
            raise ValueError(f"{index_path}: not a labelling index ({type(error).__name__}: {error})") from None
        for name, _ in self.shard_sizes:  # shards live in the label folder: an index cannot send reads elsewhere
            if not isinstance(name, str) or Path(name).name != name or name in ("", ".", ".."):
                raise ValueError(f"{index_path}: shard {name!r} is not a file of this folder (no paths allowed)")
        self._files: dict[str, h5py.File] = {}
        self._pid = os.getpid()

    def __len__(self) -> int:
        return len(self.entries)

    def incomplete(self) -> str | None:
        """What a reader says of a label folder that ``label.py`` did not finish (None: finished, or an older index
        that does not say): how many of the planned samples it holds."""
        if self.completeness is None or self.completeness[0]:
            return None
        _, labelled, failed, planned = self.completeness
        return (
            f"{self.root}: label.py did not finish this folder: {labelled} of {planned} samples labelled"
            f"{f', {failed} failed' if failed else ''}; rerun the label.py command that wrote it to finish"
        )

    def __getstate__(self):
        return {**self.__dict__, "_files": {}}

    def _file(self, name: str) -> h5py.File:
        if self._pid != os.getpid():
            self._files, self._pid = {}, os.getpid()
        if name not in self._files:
            self._files[name] = open_shard(self.root / name)
        return self._files[name]

    def __getitem__(self, index: int) -> dict:
        if not 0 <= index < len(self):
            raise IndexError(f"{self.root}: index {index} outside 0..{len(self) - 1}")
        name, position = self.entries[index]
        path = self.root / name
        group = shard_group(path, self._file(name), group_name(position))
        if group is None:
            raise ShardError(f"{path}: group {group_name(position)} missing")
        arrays = {key: shard_array(path, group, key) for key in (*REQUIRED, *OPTIONAL)}
        sample = {key: np.asarray(data[()]) for key, data in arrays.items() if data is not None}
        sample.update(
            sample_id=str(group.attrs["sample_id"]), log_id=str(group.attrs["log_id"]), dt=float(group.attrs["dt"])
        )
        return sample

    def verify(self) -> None:
        """Raise :class:`~icpflow.shards.verify.ShardError` (one line naming the shard) unless every shard of the
        index is complete, of the index's config and of its size (:func:`verify_shard`: reads every chunk)."""
        for name, count in self.shard_sizes:
            verify_shard(self.root / name, self.config_hash, count)

    def close(self) -> None:
        for handle in self._files.values():
            handle.close()
        self._files = {}


def read_shard_samples(path) -> list[dict]:
    """Every sample of one shard file as ``write_shard`` takes them (arrays by name plus an ``attrs`` dict)."""
    with open_shard(path) as f:
        groups = [shard_group(path, f, group_name(position)) for position in range(int(f.attrs["num_samples"]))]
        return [
            {**{key: shard_array(path, group, key)[()] for key in group}, "attrs": dict(group.attrs)}
            for group in groups
        ]
