"""SyntheticDataset as a reader: samples and horizons like the file readers, the LiDAR elevation spread, its config."""

import numpy as np
import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf

from icpflow.datasets.synthetic.reader import SyntheticDataset

from helpers.data import REPO

CONF = REPO / "conf" / "dataset" / "synthetic.yaml"
SMALL = {"num_sequences": 2, "frames_per_sequence": 4, "beams": 16, "azimuth_resolution_deg": 2.0}


def test_samples_are_the_scans_with_t_plus_max_horizon():
    data = SyntheticDataset("test", max_horizon=2, **SMALL)
    assert len(data) == 4 and data.metadata()["max_horizon"] == 2
    starts = []
    for index in range(len(data)):
        s, t = divmod(index, 2)
        sequence = data.sequence(s)
        one, two = data.pair(index, horizon=1), data.pair(index, horizon=2)
        np.testing.assert_array_equal(one.pc0, sequence.points[t])  # every horizon starts at scan t (tracker mode)
        np.testing.assert_array_equal(two.pc0, sequence.points[t])
        np.testing.assert_array_equal(one.pc1, sequence.points[t + 1])
        np.testing.assert_array_equal(two.pc1, sequence.points[t + 2])
        np.testing.assert_array_equal(two.flow, sequence.pair(t, 2).flow)
        assert data.sample_id(index) == f"{data.log_id(s)}/{t:06d}+1" and two.sample_id.endswith(f"{t:06d}+2")
        starts.append((s, t))
    assert starts == [(0, 0), (0, 1), (1, 0), (1, 1)]  # no sample repeats another
    with pytest.raises(IndexError, match="horizon 3 outside 1..2"):
        data.pair(0, horizon=3)
    with pytest.raises(IndexError):
        data.pair(4)


def test_default_max_horizon_is_one():
    data = SyntheticDataset("test", **SMALL)
    assert data.max_horizon == 1 and len(data) == 6
    np.testing.assert_array_equal(data.pair(5).pc1, data.sequence(1).points[3])
    with pytest.raises(IndexError, match="horizon 2 outside 1..1"):
        data.pair(0, horizon=2)


@pytest.mark.parametrize(
    "options, message",
    [
        ({"max_horizon": 4}, "max_horizon must lie in 1..3 for 4 frames per sequence, got 4"),
        ({"max_horizon": 0}, "max_horizon must lie in 1..3"),
        ({"elevation_deg": (5.0, -5.0)}, r"elevation_deg must be \[low, high\] degrees"),
        ({"elevation_deg": (-10.0,)}, r"elevation_deg must be \[low, high\] degrees"),
    ],
)
def test_bad_options(options, message):
    with pytest.raises(ValueError, match=message):
        SyntheticDataset("test", **{**SMALL, **options})


def _elevations_deg(data) -> np.ndarray:
    points = data.pair(0).pc0.astype(np.float64)
    return np.degrees(np.arctan2(points[:, 2] - data.lidar.height, np.hypot(points[:, 0], points[:, 1])))


def test_elevation_spread_sets_the_beams():
    narrow = SyntheticDataset("test", elevation_deg=(-12.0, -2.0), **SMALL)
    angles = _elevations_deg(narrow)
    assert angles.min() > -12.01 and angles.max() < -1.99  # range noise moves points along their rays only
    assert len(np.unique(angles.round(1))) == 16
    assert narrow.metadata()["elevation_deg"] == [-12.0, -2.0]
    default = SyntheticDataset("test", **SMALL)
    assert _elevations_deg(default).min() < -20 and default.metadata()["elevation_deg"] == [-25.0, 5.0]


def test_config_exposes_max_horizon_and_elevation():
    config = OmegaConf.create({"split": "val", "dataset": OmegaConf.load(CONF)})
    assert config.dataset.reader.max_horizon == 1 and config.dataset.reader.elevation_deg is None
    config.dataset.reader.merge_with({"max_horizon": 3, "elevation_deg": [-20, 5], "num_sequences": 1})
    data = instantiate(config.dataset.reader)
    assert data.max_horizon == 3 and len(data) == 2 and data.lidar.elevation_deg == (-20.0, 5.0)
