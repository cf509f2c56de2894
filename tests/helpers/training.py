"""train.py configs of the tiny student of the tests (32 x 32 pillars of 1 m, narrow encoders: a training step takes
milliseconds)."""

import json
from pathlib import Path

from hydra import compose, initialize_config_dir

CONF = Path(__file__).resolve().parents[2] / "conf"
#: the one tiny FastFlow3D of every test (``conf/model`` form; FastFlow3D's own settings where it says nothing:
#: ZeroFlow's network): [-16, 16]^2 m in 1 m pillars (32 x 32), 16 pillar channels, encoders of 8 / 16 / 32 channels
#: with one extra conv each (with 8 pillar channels the network on a masked batch and on its kept rows differ in
#: the last bit: tests/test_train.py::test_ground_removal_network_sees_non_ground_points_only asks for equality)
TINY_MODEL = {
    "_target_": "fastflow3d.network.model.FastFlow3D",
    "x_range": [-16.0, 16.0],
    "y_range": [-16.0, 16.0],
    "z_range": [-3.0, 3.0],
    "cell": 1.0,
    "pillar_channels": 16,
    "stage_channels": [8, 16, 32],
    "stage_blocks": [1, 1, 1],
    "norm": "batch",
    "decoder": "linear",
    "correlation_levels": [],
}


def tiny_model_overrides(**options) -> list[str]:
    """train.py's overrides that make its network TINY_MODEL with the model ``options`` changed."""
    return [f"model.{key}={json.dumps(value)}" for key, value in {**TINY_MODEL, **options}.items() if key != "_target_"]


#: train.py overrides of a quick run of TINY_MODEL: no loader workers, no progress bar, no export
TINY = [
    *tiny_model_overrides(),
    "data.workers=0",
    "trainer.log_every_n_steps=1",
    "trainer.enable_progress_bar=false",
    "trainer.enable_model_summary=false",
    "export.formats=[]",
]


def compose_train(*overrides):
    """The composed train.py config with ``overrides``."""
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("train", list(overrides))


def train_cfg(tmp_path, train, val, *overrides):
    """The tiny student trained on shards ``train``, validated on ``val``, its run in ``tmp_path / "run"``."""
    return compose_train(f"data.train={train}", f"data.val={val}", f"out_dir={tmp_path / 'run'}", *TINY, *overrides)


def student_module(cfg: dict):
    """The ``StudentModule`` train.py would build from the resolved config ``cfg`` (plain dict, its ``loss``,
    ``optim``, ``scheduler`` and ``metrics`` possibly changed), its input contract the synthetic frame's with the
    config's ground removal and grid."""
    from omegaconf import OmegaConf

    from fastflow3d.network.contract import InputContract, read_grid
    from fastflow3d.training.trainer import build_module

    contract = InputContract(remove_ground=bool(cfg["data"]["remove_ground"]), grid=read_grid(cfg["model"], "model"))
    parts = {"loss": cfg["loss"], "optimiser": cfg["optim"], "scheduler": cfg["scheduler"], "metrics": cfg["metrics"]}
    cfg = {**cfg, "module": {**cfg["module"], **parts}}  # as conf/train.yaml's interpolations say, after changes
    return build_module(OmegaConf.create(cfg), contract, cfg)
