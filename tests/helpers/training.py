"""train.py configs of the tiny student of the tests (32 x 32 pillars of 1 m, narrow encoders: a training step takes
milliseconds)."""

import json
from pathlib import Path

from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

CONF = Path(__file__).resolve().parents[2] / "conf"
#: the one tiny FastFlow3D of every test: ``conf/model/fastflow3d_tiny.yaml`` (its keys, over FastFlow3D's own
#: settings where it says nothing), as a ``conf/model`` dict
TINY_MODEL = {
    "_target_": "fastflow3d.network.model.FastFlow3D",
    **{
        key: value
        for key, value in OmegaConf.to_container(OmegaConf.load(CONF / "model" / "fastflow3d_tiny.yaml")).items()
        if key != "defaults"
    },
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
