"""train.py configs of a tiny student (32 x 32 pillars of 1 m, narrow encoders: a training step takes milliseconds)."""

from pathlib import Path

from hydra import compose, initialize_config_dir

CONF = Path(__file__).resolve().parents[2] / "conf"
TINY = [
    "model.x_range=[-16.0,16.0]",
    "model.y_range=[-16.0,16.0]",
    "model.cell=1.0",
    "model.pillar_channels=16",
    "model.stage_channels=[16,32,64]",
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
