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
    "+trainer.enable_progress_bar=false",
    "+trainer.enable_model_summary=false",
    "export.formats=[]",
]


def compose_train(*overrides):
    """The composed train.py config with ``overrides``."""
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("train", list(overrides))


def train_cfg(tmp_path, train, val, *overrides):
    """The tiny student trained on shards ``train``, validated on ``val``, its run in ``tmp_path / "run"``."""
    return compose_train(f"data.train={train}", f"data.val={val}", f"out_dir={tmp_path / 'run'}", *TINY, *overrides)
