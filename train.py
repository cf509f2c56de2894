"""Train the FastFlow3D student on pseudo-flow shards (see conf/train.yaml and fastflow3d.training.trainer); the same
as the console script ``fastflow3d-train`` (``fastflow3d.training.cli.train_main``). ``--help``: the options,
``--cfg job``: the whole config.

python train.py [experiment=synthetic_quick|paper|zeroflow] [data.train=<shard dir>] [data.val=<shard dir>]
    [trainer=cpu|gpu|ddp] [trainer.max_steps=N] [trainer.precision=bf16-mixed] [compile=true]
    [out_dir=<dir>] [ckpt_path=last]
"""

from fastflow3d.training.launch import train_main

if __name__ == "__main__":
    train_main()
