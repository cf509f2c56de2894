"""Label a dataset with the ICP-Flow teacher into pseudo-flow shards (see conf/label.yaml and icpflow.labelling).

    python label.py dataset=<name> [dataset.root=...] [split=train] [icpflow.<field>=...] [workers=N]
        [out_dir=...] [shard_size=32] [limit=N] [horizon=k] [tracker=true] [runner=ray] [shard_index=i num_shards=n]
"""

import sys

import hydra
from omegaconf import DictConfig

from icpflow.labelling.cli import label


@hydra.main(version_base="1.3", config_path="conf", config_name="label")
def main(cfg: DictConfig) -> None:
    status = label(cfg)
    if status:
        sys.exit(status)


if __name__ == "__main__":
    main()
