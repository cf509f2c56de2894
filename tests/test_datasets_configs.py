"""conf/dataset/*.yaml: each names a reader whose constructor takes exactly its options, and instantiates."""

import inspect
from pathlib import Path

import numpy as np
import pytest
from hydra.utils import get_class, instantiate
from omegaconf import OmegaConf

from icpflow.datasets.base import PairDataset

CONF = Path(__file__).resolve().parents[1] / "conf" / "dataset"
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
NAMES = ["av2", "waymo", "nuscenes", "zeroflow_av2", "kitti", "pairs", "sequence"]


def load(name: str, root, split: str = "val"):
    """The dataset group as the top-level config sees it: ``dataset`` plus the top-level ``split``."""
    config = OmegaConf.create({"split": split, "dataset": OmegaConf.load(CONF / f"{name}.yaml")})
    config.dataset.root = str(root)
    return config


@pytest.mark.parametrize("name", NAMES)
def test_config_shape_and_reader_options(name):
    config = load(name, "/nowhere")
    assert config.dataset.name == name
    assert config.dataset.preset in ("av2", "waymo", "nuscenes")
    assert OmegaConf.is_dict(config.dataset.teacher)
    assert OmegaConf.is_missing(OmegaConf.load(CONF / f"{name}.yaml"), "root")
    reader = OmegaConf.to_container(config.dataset.reader, resolve=True)
    cls = get_class(reader.pop("_target_"))
    assert issubclass(cls, PairDataset)
    parameters = inspect.signature(cls.__init__).parameters
    assert set(reader) <= set(parameters), f"{name}: options the reader does not take"
    assert reader["root"] == "/nowhere"


def test_pairs_config_instantiates(tmp_path):
    rng = np.random.default_rng(0)
    np.savez(tmp_path / "a.npz", pc0=rng.normal(size=(5, 3)), pc1=rng.normal(size=(6, 3)))
    dataset = instantiate(load("pairs", tmp_path).dataset.reader)
    assert len(dataset) == 1 and dataset.pair(0).pc1.shape == (6, 3)


@pytest.mark.skipif(not (DATA / "av2").is_dir(), reason=f"real AV2 sample absent: {DATA / 'av2'}")
def test_av2_config_instantiates_on_the_real_sample():
    pytest.importorskip("av2")
    dataset = instantiate(load("av2", DATA / "av2").dataset.reader)
    assert len(dataset) == 1 and dataset.name == "av2"


@pytest.mark.skipif(not (DATA / "kitti_hdl64_scans").is_dir(), reason="real KITTI scans absent")
@pytest.mark.parametrize("name", ["kitti", "sequence"])
def test_scan_folder_configs_instantiate_on_real_scans(name):
    dataset = instantiate(load(name, DATA / "kitti_hdl64_scans").dataset.reader)
    assert len(dataset) == 5
