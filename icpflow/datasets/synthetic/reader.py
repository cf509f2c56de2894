"""The embedded synthetic dataset: seeded street scenes ray-cast by a spinning LiDAR, with exact ground truth.

Nothing is read from disk. Sequence i of a split is the world of seed ``seed + SPLIT_OFFSETS[split] * SPLIT_STRIDE
+ i`` (splits are disjoint for fewer than ``SPLIT_STRIDE`` sequences), ``frames_per_sequence`` scans at
``frequency_hz`` (see :mod:`icpflow.datasets.synthetic`). As the other readers, samples are the scans t for which
t + ``max_horizon`` exists: sample ``index`` is scan ``t = index % (frames - max_horizon)`` of sequence
``index // (frames - max_horizon)``, and ``pair(index, horizon=k)`` is (t, t + k) for every k <= ``max_horizon``
(all starting at the same scan, as tracker mode needs). The LiDAR's beams spread evenly over ``elevation_deg``
(low, high) degrees (None: the beam count's default, see ``icpflow.datasets.synthetic.lidar.ELEVATIONS``). Ground truth:
full flow, classes (``icpflow.datasets.synthetic.CLASSES``, mapped onto the AV2 meta-classes by ``AV2_META_CLASSES``),
instance ids (0 = background; parked vehicles have their own), dynamic (world speed > 0.5 m/s), ground masks, poses
and timestamps. Sequences are generated on demand; the last one is kept, so iterating in order costs one
generation per sequence.
"""

from __future__ import annotations

import numpy as np

from icpflow.core.frame_pair import FramePair, FrameSequence
from icpflow.datasets.base import PairDataset
from icpflow.datasets.synthetic.drive import sequence
from icpflow.datasets.synthetic.lidar import SENSOR_HEIGHT, Lidar
from icpflow.datasets.synthetic.scene import AV2_META_CLASSES, build_scene

SPLIT_OFFSETS = {"train": 0, "val": 1, "test": 2}
SPLIT_STRIDE = 1_000_000


class SyntheticDataset(PairDataset):
    """Frame pairs of generated sequences (see the module docstring). Picklable; nothing generated up front."""

    name = "synthetic"
    class_to_meta = AV2_META_CLASSES

    def __init__(
        self,
        split: str = "val",
        num_sequences: int = 4,
        frames_per_sequence: int = 5,
        beams: int = 64,
        frequency_hz: float = 10.0,
        seed: int = 0,
        azimuth_resolution_deg: float = 0.2,
        max_range: float = 75.0,
        range_noise: float = 0.02,
        dropout: float = 0.03,
        sensor_height: float = SENSOR_HEIGHT,
        density: float = 1.0,
        max_horizon: int = 1,
        elevation_deg: tuple[float, float] | None = None,
    ) -> None:
        if split not in SPLIT_OFFSETS:
            raise ValueError(f"synthetic: unknown split {split!r}, expected one of {sorted(SPLIT_OFFSETS)}")
        if not 1 <= num_sequences <= SPLIT_STRIDE:
            raise ValueError(f"synthetic: num_sequences must lie in 1..{SPLIT_STRIDE}, got {num_sequences}")
        if frames_per_sequence < 2:
            raise ValueError(f"synthetic: frames_per_sequence must be >= 2, got {frames_per_sequence}")
        if not 1 <= max_horizon < frames_per_sequence:
            raise ValueError(
                f"synthetic: max_horizon must lie in 1..{frames_per_sequence - 1} for "
                f"{frames_per_sequence} frames per sequence, got {max_horizon}"
            )
        if elevation_deg is not None:
            elevation_deg = tuple(float(v) for v in elevation_deg)
            if len(elevation_deg) != 2 or not -90 < elevation_deg[0] < elevation_deg[1] < 90:
                raise ValueError(
                    f"synthetic: elevation_deg must be [low, high] degrees, -90 < low < high < 90, "
                    f"got {list(elevation_deg)}"
                )
        self.split = split
        self.num_sequences = int(num_sequences)
        self.frames = int(frames_per_sequence)
        self.frequency_hz = float(frequency_hz)
        self.seed = int(seed)
        self.density = float(density)
        self.lidar = Lidar(
            beams=int(beams),
            azimuth_resolution_deg=float(azimuth_resolution_deg),
            max_range=float(max_range),
            range_noise=float(range_noise),
            dropout=float(dropout),
            height=float(sensor_height),
            elevation_deg=elevation_deg,
        )
        self.max_horizon = int(max_horizon)
        self._cached: tuple[int, FrameSequence] | None = None

    def __len__(self) -> int:
        return self.num_sequences * self._per_sequence()

    def _per_sequence(self) -> int:
        """Samples per sequence: the scans t with t + max_horizon in the sequence."""
        return self.frames - self.max_horizon

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_cached": None}

    def sequence_seed(self, sequence_index: int) -> int:
        """The world seed of sequence ``sequence_index`` of this split."""
        return self.seed + SPLIT_OFFSETS[self.split] * SPLIT_STRIDE + sequence_index

    def log_id(self, sequence_index: int) -> str:
        return f"synthetic-{self.split}-{self.sequence_seed(sequence_index)}-{self.lidar.beams}b"

    def sample_id(self, index: int) -> str:
        self._check(index)
        s, t = divmod(index, self._per_sequence())
        return f"{self.log_id(s)}/{t:06d}+1"

    def metadata(self) -> dict:
        return {
            **super().metadata(),
            "split": self.split,
            "num_sequences": self.num_sequences,
            "frames": self.frames,
            "frequency_hz": self.frequency_hz,
            "seed": self.seed,
            "beams": self.lidar.beams,
            "azimuth_resolution_deg": self.lidar.azimuth_resolution_deg,
            "max_range": self.lidar.max_range,
            "range_noise": self.lidar.range_noise,
            "dropout": self.lidar.dropout,
            "sensor_height": self.lidar.height,
            "density": self.density,
            "elevation_deg": np.degrees(self.lidar.elevations()[[0, -1]]).round(6).tolist(),
        }

    def pair(self, index: int, horizon: int = 1) -> FramePair:
        self._check(index)
        if not 1 <= horizon <= self.max_horizon:
            raise IndexError(f"{self.name}: horizon {horizon} outside 1..{self.max_horizon}")
        s, t = divmod(index, self._per_sequence())
        return self.sequence(s).pair(t, horizon)

    def sequence(self, sequence_index: int) -> FrameSequence:
        """Sequence ``sequence_index`` as a FrameSequence (generated, or the cached last one)."""
        if self._cached is None or self._cached[0] != sequence_index:
            scene = build_scene(self.sequence_seed(sequence_index), self.frames, self.frequency_hz, self.density)
            self._cached = (sequence_index, sequence(scene, self.lidar, log_id=self.log_id(sequence_index)))
        return self._cached[1]

    def _check(self, index: int) -> None:
        if not 0 <= index < len(self):
            raise IndexError(f"{self.name}: index {index} outside 0..{len(self) - 1}")
