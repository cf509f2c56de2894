"""Label a dataset with the ICP-Flow teacher into pseudo-flow shards (see conf/label.yaml and icpflow.labelling).

python label.py dataset=<name> [dataset.root=...] [split=train] [icpflow.<field>=...] [workers=N]
    [out_dir=...] [shard_size=32] [limit=N] [horizon=k] [tracker=true] [runner=ray] [shard_index=i num_shards=n]
python label.py -m shard_index=0,1,2,3 num_shards=4 ... [hydra/launcher=submitit_slurm]   # one job per part
"""

import sys

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from icpflow.console import quiet
from icpflow.errors_and_signals import reported, run
from icpflow.labelling.cli import label
from icpflow.options import register

register()  # label_schema in Hydra's ConfigStore: the structured config conf/label.yaml extends


@hydra.main(version_base="1.3", config_path="conf", config_name="label")
def main(cfg: DictConfig) -> None:
    quiet()
    with reported("label"):
        status = label(cfg)
        if status == 1 and HydraConfig.get().mode == RunMode.MULTIRUN:
            return  # failed samples are in failures.jsonl and the summary; the sweep goes on with its other jobs
        if status:
            sys.exit(status)


if __name__ == "__main__":
    run("label", main)
