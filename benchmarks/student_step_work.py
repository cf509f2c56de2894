"""CPU work of one training step of the student, in one process on one thread (``time.process_time``, so the figure
holds on a shared machine): the network's forward + loss + backward + Adam step in the run's precision (bf16 autocast or
float32, ``auto`` resolved as ``train.py`` does) on a real batch, and the DataLoader's work per sample (read, augment,
compensate, and, where the tree has it, the crop to the network's points). Run by ``bench_training_step --work`` in each
source tree (``python -m benchmarks.student_step_work <conf dir> <train> <val> <batches> [overrides]``, the tree the
working directory): it uses only that tree's own code."""

import json
import statistics
import sys
import time

import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf


def main() -> None:
    conf_dir, train, val, runs = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
    overrides = sys.argv[5:]
    torch.set_num_threads(1)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")
    from fastflow3d.training import data as data_module
    from fastflow3d.training.student_module import StudentModule

    try:  # the schema conf/train.yaml extends (trees older than issue 32 have none)
        from fastflow3d.training.options import register
    except ImportError:
        pass
    else:
        register()
    with initialize_config_dir(config_dir=conf_dir, version_base="1.3"):
        cfg = compose("train", [f"data.train={train}", f"data.val={val}", *overrides])
    plain = OmegaConf.to_container(cfg, resolve=True)
    torch.manual_seed(0)
    from fastflow3d.training import trainer

    if hasattr(trainer, "build_module"):  # a tree with the input contract: the module as train.py builds it
        from fastflow3d.network.contract import InputContract, read_grid

        contract = InputContract(
            remove_ground=bool(plain["data"]["remove_ground"]), grid=read_grid(plain["model"], "m")
        )
        module = trainer.build_module(cfg, contract, plain).train()
    else:
        module = StudentModule(plain).train()
    options = plain["data"]
    if hasattr(data_module.ShardDataModule, "from_config"):
        datamodule = data_module.ShardDataModule.from_config(options, module.contract)
    else:
        datamodule = data_module.ShardDataModule(
            options["train"], options["val"], options["batch_size"], 0, options["augment"]
        )
    datamodule.setup("fit")
    dataset, size = datamodule.train_set, options["batch_size"]
    precision = str(plain["trainer"]["precision"])
    try:  # trees with trainer.precision=auto resolve it as train.py does
        from fastflow3d.training.precision import choose_precision
    except ImportError:
        pass
    else:
        precision = choose_precision(precision, "cpu")[0]
    bf16 = "bf16" in precision
    sample_times, step_times = [], []
    optimiser = torch.optim.Adam(module.parameters(), lr=1e-4)
    for run in range(runs + 1):
        tic = time.process_time()
        samples = [dataset[(run * size + i) % len(dataset)] for i in range(size)]
        sample_times.append((time.process_time() - tic) / size)
        batch = data_module.collate(samples)
        tic = time.process_time()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            pred, valid = module(batch)
            loss = module.loss(pred, valid, batch)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        step_times.append(time.process_time() - tic)
    print(
        json.dumps(
            {
                "step": statistics.median(step_times[1:]),
                "sample": statistics.median(sample_times[1:]),
                "batch": size,
                "precision": precision,
            }
        )
    )


if __name__ == "__main__":
    main()
