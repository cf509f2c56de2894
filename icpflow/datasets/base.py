"""The one plug-in interface every dataset reader implements.

A reader is cheap to construct (it lists files, it does not load them) and picklable, so worker processes can
each open their own copy. ``pair(index, horizon=k)`` returns the :class:`~icpflow.frames.FramePair` from scan t
to scan t + k of the index-th sample, converted into the project's conventions at this boundary.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

from icpflow.frames import FramePair


class PairDataset(ABC):
    """Indexable frame pairs. Subclasses implement ``__len__``, ``pair`` and ``sample_id``."""

    #: short name used in output paths and logs, e.g. ``"synthetic"`` or ``"av2"``
    name: str = "dataset"
    #: largest frame gap ``k`` that ``pair(index, horizon=k)`` supports
    max_horizon: int = 1
    #: the readers' ``classes`` -> AV2 bucketed-metric meta-class (``icpflow.metrics.META_CLASSES``); None: unknown
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

    def metadata(self) -> dict:
        """Facts about the dataset that end up in shard attributes and reports."""
        return {"name": self.name, "size": len(self), "max_horizon": self.max_horizon}


def sample_id_or_index(dataset, index: int) -> str:
    """``dataset.sample_id(index)`` for failure records, or ``index <index>`` when even that fails (the id itself
    may be what is broken)."""
    try:
        return dataset.sample_id(index)
    except Exception:
        return f"index {index}"


def too_short(runs: list[tuple[str, int]], max_horizon: int, unit: str = "scans") -> str:
    """Why runs of consecutive scans (``(name, scan count)``, e.g. a log and its sweeps) give no pair (t, t +
    ``max_horizon``): "" if some run is long enough, else one line naming them, e.g. "log abc has 2 sweeps: a pair
    2 apart needs at least 3"."""
    if not runs or any(count > max_horizon for _, count in runs):
        return ""
    shown = ", ".join(f"{name} has {count}" for name, count in runs[:3]) + (" ..." if len(runs) > 3 else "")
    return f"{shown} {unit}: a pair {max_horizon} apart needs at least {max_horizon + 1}"
