"""Train the FastFlow3D student on pseudo-flow shards (see conf/train.yaml and fastflow3d.training.trainer).

python train.py [experiment=synthetic_quick|paper|zeroflow] [data.train=<shard dir>] [data.val=<shard dir>]
    [trainer=cpu|gpu|ddp] [trainer.max_steps=N] [trainer.precision=bf16-mixed] [compile=true]
    [out_dir=<dir>] [ckpt_path=last]
"""

import hydra
from omegaconf import DictConfig

from fastflow3d.training.options import register
from fastflow3d.training.run_folder import TrainError
from fastflow3d.training.trainer import fit
from icpflow.console import quiet
from icpflow.errors_and_signals import reported, run

register()  # train_schema in Hydra's ConfigStore: the structured config conf/train.yaml extends


@hydra.main(version_base="1.3", config_path="conf", config_name="train")
def main(cfg: DictConfig) -> None:
    quiet()
    with reported("train", TrainError):
        fit(cfg)


if __name__ == "__main__":
    run("train", main)
