"""Label a dataset with the ICP-Flow teacher into pseudo-flow shards (see conf/label.yaml and icpflow.labelling); the
same as the console script ``icpflow-label`` (``icpflow.labelling.cli.main``). ``--help``: the options, ``--cfg job``:
the whole config.

python label.py dataset=<name> [dataset.root=...] [split=train] [icpflow.<field>=...] [workers=N]
    [out_dir=...] [shard_size=32] [limit=N] [horizon=k] [tracker=true] [runner=ray] [shard_index=i num_shards=n]
python label.py -m shard_index=0,1,2,3 num_shards=4 ... [hydra/launcher=submitit_slurm]   # one job per part
"""

from icpflow.labelling.launch import main

if __name__ == "__main__":
    main()
