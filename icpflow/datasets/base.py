"""The one plug-in interface every dataset reader implements.

A reader is cheap to construct (it lists files, it does not load them) and picklable, so worker processes can
each open their own copy. ``pair(index, horizon=k)`` returns the :class:`~icpflow.core.frame_pair.FramePair` from scan t
to scan t + k of the index-th sample, converted into the project's conventions at this boundary.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from pathlib import Path

from icpflow.core.frame_pair import FramePair
from icpflow.core.stops import raise_stop_behind


class PairDataset(ABC):
    """Indexable frame pairs. Subclasses implement ``__len__``, ``pair`` and ``sample_id``."""

    #: short name used in output paths and logs, e.g. ``"synthetic"`` or ``"av2"``
    name: str = "dataset"
    #: largest frame gap ``k`` that ``pair(index, horizon=k)`` supports
    max_horizon: int = 1
    #: the readers' ``classes`` -> AV2 bucketed-metric meta-class (``icpflow.evaluation.metrics.META_CLASSES``); None:
    #: unknown
    class_to_meta: dict[int, str] | None = None

    @abstractmethod
    def __len__(self) -> int: ...

    @abstractmethod
    def pair(self, index: int, horizon: int = 1) -> FramePair:
        """The pair (t, t + horizon) of sample ``index``."""

    @abstractmethod
    def sample_id(self, index: int) -> str:
        """A stable id for sample ``index`` (used in shards and failure records), without loading it."""

    def __getitem__(self, index: int) -> FramePair:
        if not 0 <= index < len(self):
            raise IndexError(f"{self.name}: index {index} outside 0..{len(self) - 1}")
        return self.pair(index)

    def why_empty(self) -> str:
        """Why the reader has no samples, one line ("" when it has some or cannot tell); readers whose samples need
        ``max_horizon`` more scans than t say which runs of scans were too short (:func:`too_short`)."""
        return ""

    def drive_without_poses(self):
        """``(paths, read)`` when the reader's samples are the consecutive scans of one drive with no ego motion
        of its own (a recording without poses): the scans' files in order and ``read(i)``, scan i as (N, 3) float32
        in the height frame; ``label.py`` then estimates the drive's trajectory once
        (``icpflow.labelling.trajectory``) and hands it back through :meth:`use_ego_motions`. None (the default):
        the reader gives its ego motion, or its pairs are not one drive."""
        return None

    def use_ego_motions(self, motions) -> None:
        """Take the drive's ego motion (:meth:`drive_without_poses`): ``motions`` (T - 1, 4, 4) float64, scan i to
        scan i + 1, NaN where there is none."""
        raise NotImplementedError(f"{self.name}: the reader gives its own ego motion")

    def metadata(self) -> dict:
        """Facts about the dataset that end up in shard attributes and reports."""
        return {"name": self.name, "size": len(self), "max_horizon": self.max_horizon}


class IndexedDataset(PairDataset):
    """The shared indexing of the readers whose samples are listed once, at construction: the frames t of sequences
    for which frame t + ``max_horizon`` exists (:meth:`_index_sequences`: AV2 logs, KITTI sequences), or one file
    per sample (:meth:`_index_files`: pairs, ZeroFlow dumps). ``_index[i]`` is sample i: ``(sequence, t)`` or the
    file's path. ``_cache`` holds what this process has read for reuse (a sequence's poses, a log's tables); a
    pickled copy starts with it empty, so each worker process reads its own."""

    _index: list
    _cache: dict

    def _index_sequences(self, sequences: list[tuple[object, list]]) -> None:
        """Index ``sequences``: ``[(sequence, frames)]`` in sample order, each frame list in time order (a sequence
        given as a folder and frames as files are named by their name and stem in :meth:`sample_id`)."""
        self._sequences = sequences
        self._index = [(s, t) for s, (_, frames) in enumerate(sequences) for t in range(len(frames) - self.max_horizon)]
        self._cache = {}

    def _index_files(self, files: list[Path]) -> None:
        """Index one sample per file of ``files`` (kept as ``files``), in that order."""
        self.files = files
        self._index = files
        self._cache = {}

    def _frames(self, index: int) -> tuple[object, list, int]:
        """``(sequence, frames, t)`` of sample ``index`` of a sequence reader."""
        s, t = self._index[index]
        sequence, frames = self._sequences[s]
        return sequence, frames, t

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_cache": {}}

    def __len__(self) -> int:
        return len(self._index)

    def sample_id(self, index: int) -> str:
        """``<sequence>/<frame t>`` of a sequence reader, the file's stem of a file reader."""
        entry = self._index[index]
        if not isinstance(entry, tuple):
            return self._file_id(entry)
        sequence, frames, t = self._frames(index)
        name, frame = (sequence.name if isinstance(sequence, Path) else sequence), frames[t]
        return f"{name}/{frame.stem if isinstance(frame, Path) else frame}"

    def _file_id(self, path: Path) -> str:
        """The sample id of a file reader's sample file ``path``."""
        return path.stem


def sample_id_or_index(dataset, index: int) -> str:
    """``dataset.sample_id(index)`` for failure records, or ``index <index>`` when even that fails (the id itself
    may be what is broken)."""
    try:
        return dataset.sample_id(index)
    except Exception as error:
        raise_stop_behind(error)
        return f"index {index}"


def too_short(runs: list[tuple[str, int]], max_horizon: int, unit: str = "scans") -> str:
    """Why runs of consecutive scans (``(name, scan count)``, e.g. a log and its sweeps) give no pair (t, t +
    ``max_horizon``): "" if some run is long enough, else one line naming them, e.g. "log abc has 2 sweeps: a pair
    2 apart needs at least 3"."""
    if not runs or any(count > max_horizon for _, count in runs):
        return ""
    shown = ", ".join(f"{name} has {count}" for name, count in runs[:3]) + (" ..." if len(runs) > 3 else "")
    return f"{shown} {unit}: a pair {max_horizon} apart needs at least {max_horizon + 1}"
