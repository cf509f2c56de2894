"""conf/dataset/*.yaml: each names a reader whose constructor takes exactly its options, and instantiates."""

import inspect

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import get_class, instantiate
from omegaconf import OmegaConf

from icpflow.datasets.base import PairDataset
from icpflow.scans.preprocess import Preprocessing
from icpflow.teacher import ICPFlowConfig
from icpflow.teacher.config import teacher_config

from helpers.data import REPO, needs_shared, shared

CONF = REPO / "conf" / "dataset"
NAMES = ["av2", "waymo", "nuscenes", "zeroflow_av2", "kitti", "pairs", "sequence", "synthetic"]
FILE_LESS = {"synthetic"}  # generated: root is null, nothing is read


def load(name: str, root, split: str = "val"):
    """The dataset group as the top-level config sees it: ``dataset`` plus the top-level ``split``."""
    config = OmegaConf.create({"split": split, "dataset": OmegaConf.load(CONF / f"{name}.yaml")})
    if name not in FILE_LESS:
        config.dataset.root = str(root)
    return config


@pytest.mark.parametrize("name", NAMES)
def test_config_shape_and_reader_options(name):
    config = load(name, "/nowhere")
    assert config.dataset.name == name
    assert config.dataset.preset in ("av2", "waymo", "nuscenes")
    assert OmegaConf.is_dict(config.dataset.teacher)
    assert config.dataset.eval_crop in (32.0, 51.2)
    raw = OmegaConf.load(CONF / f"{name}.yaml")
    assert raw.root is None if name in FILE_LESS else OmegaConf.is_missing(raw, "root")
    reader = OmegaConf.to_container(config.dataset.reader, resolve=True)
    cls = get_class(reader.pop("_target_"))
    assert issubclass(cls, PairDataset)
    parameters = inspect.signature(cls.__init__).parameters
    assert set(reader) <= set(parameters), f"{name}: options the reader does not take"
    assert name in FILE_LESS or reader["root"] == "/nowhere"


def _given(block: dict) -> dict:
    """``block`` without its null fields and the blocks left empty."""
    given = {key: _given(value) if isinstance(value, dict) else value for key, value in block.items()}
    return {key: value for key, value in given.items() if value not in (None, {})}


def _composed(*overrides):
    with initialize_config_dir(config_dir=str(CONF.parent), version_base="1.3"):
        return compose("label", list(overrides))


@pytest.mark.parametrize("name", NAMES)
def test_teacher_block_names_teacher_fields(name):
    """dataset.teacher holds ICPFlowConfig fields only; they land in the teacher config over the preset."""
    cfg = _composed(f"dataset={name}", "dataset.root=/nowhere")
    teacher = teacher_config(cfg)
    block = _given(OmegaConf.to_container(cfg.dataset.teacher, resolve=True))  # null: the preset's value
    assert teacher == ICPFlowConfig.preset(cfg.dataset.preset, **block)
    assert (
        teacher_config(
            _composed(f"dataset={name}", "dataset.root=/nowhere", "icpflow.clustering.min_cluster_size=7")
        ).clustering.min_cluster_size
        == 7
    )


def test_unknown_teacher_key_is_an_error():
    cfg = _composed("dataset=kitti", "dataset.root=/nowhere", "+dataset.teacher.num_frames=5")
    with pytest.raises(
        ValueError, match="dataset kitti: dataset.teacher has keys that are not ICPFlowConfig fields: num_frames"
    ):
        teacher_config(cfg)


#: the dataset configs that state one sensor height, the teacher's ground block following it: (its key, its value)
ONE_HEIGHT = {
    "kitti": ("dataset.reader.sensor_height", 1.73),
    "sequence": ("dataset.teacher.ground.sensor_height", 1.723),  # the reader's is auto: this is the av2 preset's
    "synthetic": ("dataset.reader.sensor_height", 1.9),
}


@pytest.mark.parametrize("name", sorted(ONE_HEIGHT))
def test_patchwork_offset_follows_the_one_sensor_height(name):
    """The height is written once; in the height frame (ground near z = 0) Patchwork++ gets that sensor height and
    the scan shifted down by it (ground at -sensor_height); overriding the height moves both."""
    key, stated = ONE_HEIGHT[name]
    assert (CONF / f"{name}.yaml").read_text().count(str(stated)) == 1
    for overrides, height in (([], stated), ([f"{key}=2.5"], 2.5)):
        cfg = _composed(f"dataset={name}", "dataset.root=/nowhere", *overrides)
        assert OmegaConf.select(cfg, key) == height
        teacher = teacher_config(cfg)
        assert (teacher.ground.sensor_height, teacher.ground.patchwork_z_offset) == (height, -height)
        assert Preprocessing.from_teacher(teacher).frame.ground_z == 0.0


def test_synthetic_config_instantiates():
    dataset = instantiate(load("synthetic", None).dataset.reader)
    assert len(dataset) == 8 and dataset.split == "val"


def test_pairs_config_instantiates(tmp_path):
    rng = np.random.default_rng(0)
    np.savez(tmp_path / "a.npz", pc0=rng.normal(size=(5, 3)), pc1=rng.normal(size=(6, 3)))
    dataset = instantiate(load("pairs", tmp_path).dataset.reader)
    assert len(dataset) == 1 and dataset.pair(0).pc1.shape == (6, 3)


@needs_shared("av2", what="the real Argoverse 2 sample")
def test_av2_config_instantiates_on_the_real_sample():
    pytest.importorskip("av2")
    dataset = instantiate(load("av2", shared("av2")).dataset.reader)
    assert len(dataset) == 1 and dataset.name == "av2"


@needs_shared("kitti_hdl64_scans", what="the real KITTI HDL-64 scans")
@pytest.mark.parametrize("name", ["kitti", "sequence"])
def test_scan_folder_configs_instantiate_on_real_scans(name):
    dataset = instantiate(load(name, shared("kitti_hdl64_scans")).dataset.reader)
    assert len(dataset) == 5


def test_a_config_naming_a_moved_reader_opens_it_by_todays_path(tmp_path):
    """A dataset config of the last release (``icpflow.datasets.sequence.ScanSequenceDataset``) opens the reader by
    today's path, without the old path's DeprecationWarning; the run's config names today's path afterwards."""
    import warnings

    from icpflow.datasets.from_config import open_dataset

    rng = np.random.default_rng(0)
    for index in range(3):
        rng.normal(size=(50, 4)).astype(np.float32).tofile(tmp_path / f"{index:06d}.bin")
    cfg = load("sequence", tmp_path)
    cfg.dataset.reader._target_ = "icpflow.datasets.sequence.ScanSequenceDataset"
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        dataset = open_dataset(cfg)
    assert type(dataset).__module__ == "icpflow.datasets.scan_folder" and len(dataset) == 2
    assert cfg.dataset.reader._target_ == "icpflow.datasets.scan_folder.ScanSequenceDataset"
