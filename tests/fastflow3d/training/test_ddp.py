"""Data-parallel training proven on this machine (issue 34): 2 DDP processes over gloo (``trainer=ddp_cpu``) learn
what one process learns with the same samples per step, see each sample once per epoch, validate on the whole val
set, write once, stop together on SIGTERM and resume where they stopped, under Lightning's own launcher, a simulated
SLURM ``srun`` and ``torchrun``.

One set of runs per module, on the tiny network with GroupNorm (``model.norm=group``: each process's BatchNorm would
normalise its own share of the batch, a different computation from one process's) and float32:

- ``stopped``: ``train.py trainer=ddp_cpu data.batch_size=1`` (Lightning starts rank 1), SIGTERM to the launcher
  before step 5; then ``resumed``: ``ckpt_path=last`` as 2 SLURM tasks (the variables ``srun`` sets);
- ``torchrun``: the same 8 steps from scratch under ``torchrun --nproc_per_node=2``;
- ``single``: one process (this one), ``data.batch_size=2``, 8 steps.

The tests of these runs are marked slow (``pytest --run-slow``, as CI runs them).
"""

import json
import os
import random
import signal
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

from fastflow3d.training.augment import Augmentation
from fastflow3d.training.data import Draw, EpochOrder, ShardDataModule, StudentDataset
from fastflow3d.training.trainer import fit
from icpflow.datasets.synthetic.reader import SyntheticDataset

from helpers.data import REPO
from helpers.labelling import TESTS_ENV
from helpers.shards import write_pseudo_labels
from helpers.training import TINY, compose_train

STEPS = 8  # 2 epochs of 8 training samples at 2 per step
EXACT = [
    "model.norm=group",
    "trainer.precision=32-true",
    f"trainer.max_steps={STEPS}",
    "trainer.val_check_interval=2",
    "metrics.bev_every=1",
    "trainer.num_sanity_val_steps=0",
    "export.formats=[onnx]",
]
TWO = ["trainer=ddp_cpu", "data.batch_size=1"]


def _command(out: Path, data: Path, *overrides, launcher=()) -> list[str]:
    record = [
        "+callbacks.record._target_=helpers.ddp.RecordSamples",
        f"+callbacks.record.folder={out / 'record'}",
    ]
    paths = [f"data.train={data / 'train'}", f"data.val={data / 'val'}", f"out_dir={out}"]
    script = [str(REPO / "train.py"), *paths, *TINY, *EXACT, *record, *overrides]
    return [sys.executable, *launcher, *script]


def _run(args, env=None) -> subprocess.CompletedProcess:
    return subprocess.run(args, cwd=REPO, env=env or TESTS_ENV, capture_output=True, text=True, timeout=300)


def _srun(args) -> list[subprocess.CompletedProcess]:
    """``args`` as 2 tasks of a SLURM job step on one node: the variables ``srun`` sets for each task."""
    job = str(random.randint(100000, 999999))
    tasks = []
    for rank in range(2):
        env = {
            **TESTS_ENV,
            "SLURM_JOB_ID": job,
            "SLURM_JOB_NAME": "train",
            "SLURM_NTASKS": "2",
            "SLURM_NTASKS_PER_NODE": "2",
            "SLURM_NNODES": "1",
            "SLURM_NODEID": "0",
            "SLURM_NODELIST": "localhost",
            "SLURM_PROCID": str(rank),
            "SLURM_LOCALID": str(rank),
        }
        tasks.append(
            subprocess.Popen(args, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        )
    results = []
    for task in tasks:
        out, err = task.communicate(timeout=300)
        results.append(subprocess.CompletedProcess(task.args, task.returncode, out, err))
    return results


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("ddp")
    train = SyntheticDataset(
        split="train", num_sequences=3, frames_per_sequence=4, beams=32, azimuth_resolution_deg=2.0
    )
    val = SyntheticDataset(split="val", num_sequences=1, frames_per_sequence=6, beams=32, azimuth_resolution_deg=2.0)
    write_pseudo_labels(root / "data" / "train", [train.pair(i) for i in range(8)])
    write_pseudo_labels(root / "data" / "val", [val.pair(i) for i in range(5)])  # odd: shares of 3 and 2
    data = root / "data"
    two, single, elastic = root / "two", root / "single", root / "torchrun"
    stopped = _run(_command(two, data, *TWO, "ckpt_path=auto", "+callbacks.record.sigterm_at_step=5"))
    stopped_step = torch.load(two / "checkpoints" / "last.ckpt", weights_only=True, mmap=True)["global_step"]
    resumed = _srun(_command(two, data, *TWO, "ckpt_path=auto"))
    torchrun = ["-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2"]
    elastic_run = _run(_command(elastic, data, *TWO, "export.formats=[]", "metrics.bev_every=0", launcher=torchrun))
    single_run = fit(compose_train(*_command(single, data, "data.batch_size=2", "export.formats=[]")[2:]))
    return SimpleNamespace(
        root=root,
        two=two,
        single=single,
        elastic=elastic,
        stopped=stopped,
        stopped_step=stopped_step,
        resumed=resumed,
        elastic_run=elastic_run,
        single_run=single_run,
    )


def _records(out: Path) -> dict[int, list[dict]]:
    return {
        rank: [json.loads(line) for line in (out / "record" / f"rank{rank}.jsonl").read_text().splitlines()]
        for rank in (0, 1)
        if (out / "record" / f"rank{rank}.jsonl").exists()
    }


def _weights(out: Path) -> dict:
    return torch.load(out / "checkpoints" / "last.ckpt", weights_only=True)


def _scalars(out: Path) -> dict[tuple[str, int], float]:
    """Every scalar (tag, step) of a run's TensorBoard event files (all its launches)."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    values = {}
    for events in sorted((out / "tensorboard").rglob("events.out.tfevents.*")):
        accumulator = EventAccumulator(str(events))
        accumulator.Reload()
        for tag in accumulator.Tags()["scalars"]:
            values.update({(tag, event.step): event.value for event in accumulator.Scalars(tag)})
    return values


def _ok(result: subprocess.CompletedProcess) -> None:
    assert result.returncode == 0, result.stderr[-3000:]


@pytest.mark.slow
def test_all_runs_finish(runs):
    for result in (*runs.resumed, runs.elastic_run):
        _ok(result)
    assert runs.single_run.global_step == STEPS
    assert runs.stopped.returncode == 128 + signal.SIGTERM, runs.stopped.stderr[-3000:]


# ------------------------------------------------------------------------------------ (a) same weights, same order


@pytest.mark.slow
@pytest.mark.parametrize("run", ["two", "elastic"])
def test_two_processes_of_batch_b_learn_what_one_process_of_batch_2b_learns(runs, run):
    """Issue 34.1(a): 2 x batch 1 (stopped by SIGTERM and resumed as SLURM tasks; or under torchrun) and 1 x batch 2
    end at the same weights after 8 steps (augmentation on: its draws depend on the sample and epoch, not the
    rank), within float32 reduction order (measured 7e-7), with the same optimiser and schedule state."""
    ours, theirs = _weights(getattr(runs, run)), _weights(runs.single)
    assert ours["global_step"] == theirs["global_step"] == STEPS
    for name, tensor in theirs["state_dict"].items():
        torch.testing.assert_close(ours["state_dict"][name], tensor, atol=1e-5, rtol=1e-4, msg=name)
    assert ours["lr_schedulers"] == theirs["lr_schedulers"]
    moment = [state["exp_avg_sq"] for state in theirs["optimizer_states"][0]["state"].values()]
    ours_moment = [state["exp_avg_sq"] for state in ours["optimizer_states"][0]["state"].values()]
    for a, b in zip(ours_moment, moment):
        torch.testing.assert_close(a, b, atol=1e-9, rtol=1e-3)


@pytest.mark.slow
def test_each_step_of_two_ranks_holds_the_samples_of_one_process_step(runs):
    """Issue 34.1(a, b): at every step the two ranks' samples are the one process's batch (same data order), and in
    each epoch every training sample is seen once across the ranks."""
    single = {record["step"]: record for record in _records(runs.single)[0]}
    for out in (runs.two, runs.elastic):
        records = _records(out)
        assert set(records) == {0, 1}
        by_step = {}
        for rank in (0, 1):
            assert [r["step"] for r in records[rank]] == list(range(STEPS))  # the resume continued at its step
            for record in records[rank]:
                by_step.setdefault(record["step"], []).extend(record["samples"])
        for step, samples in by_step.items():
            assert sorted(samples) == sorted(single[step]["samples"]), step
        for epoch in (0, 1):
            seen = [s for step, samples in by_step.items() if single[step]["epoch"] == epoch for s in samples]
            assert len(seen) == len(set(seen)) == 8


def test_the_training_order_splits_one_permutation_among_ranks_and_resumes_inside_an_epoch(tmp_path):
    """Issue 34.1(b) without processes: with 9 samples and 2 or 3 ranks, each epoch's permutation is dealt round
    robin, nothing is repeated and only the permutation's last ``9 % ranks`` are left out (other ones each epoch);
    the random draws of a sample depend on the seed, epoch and index only; a resume starts after the batches
    trained."""
    dataset = list(range(9))
    for world in (1, 2, 3):
        left_out = []
        for epoch in range(4):
            shares = []
            for rank in range(world):
                order = EpochOrder(dataset, world, rank, seed=7)
                order.set_epoch(epoch)
                shares.append([draw.index for draw in order])
            seen = [index for share in shares for index in share]
            assert len(seen) == len(set(seen)) == 9 - 9 % world
            assert len({len(share) for share in shares}) == 1
            one = EpochOrder(dataset, 1, 0, seed=7)
            one.set_epoch(epoch)
            assert [draw.index for draw in one][: len(seen)] == [
                shares[i % world][i // world] for i in range(len(seen))
            ]
            left_out.append(tuple(sorted(set(dataset) - set(seen))))
        if world == 2:
            assert len(set(left_out)) > 1
    order = EpochOrder(dataset, 2, 1, seed=7, resume=(3, 2, 1))
    order.set_epoch(3)
    full = EpochOrder(dataset, 2, 1, seed=7)
    full.set_epoch(3)
    assert list(order) == list(full)[2:] and len(order) == len(full) == 4
    order.set_epoch(4)  # the epochs after the resumed one start at their first sample
    full.set_epoch(4)
    assert list(order) == list(full)
    assert Draw(3, (7, 1)).rng().random() == Draw(3, (7, 1)).rng().random() != Draw(3, (7, 2)).rng().random()
    pair = SyntheticDataset(split="train", num_sequences=1, frames_per_sequence=2, beams=32).pair(0)
    samples = StudentDataset(write_pseudo_labels(tmp_path / "train", [pair] * 4), augment=Augmentation(yaw_deg=20.0))
    assert torch.equal(samples[Draw(3, (7, 1))]["pc0"], samples[Draw(3, (7, 1))]["pc0"])


@pytest.mark.slow
def test_the_data_module_saves_where_the_epoch_stopped(runs):
    """The checkpoint holds the training order's position (epoch, batches of it trained), which ``load_state_dict``
    hands the next ``train_dataloader``."""
    saved = torch.load(runs.two / "checkpoints" / "last.ckpt", weights_only=True)
    assert saved["ShardDataModule"] == {"epoch": 1, "batches": 4}
    module = ShardDataModule(runs.root / "data" / "train", runs.root / "data" / "val", batch_size=1, seed=3)
    module.load_state_dict({"epoch": 1, "batches": 2})
    module.setup("fit")
    sampler = module.train_dataloader().sampler
    assert sampler.resume == (1, 2, 1) and sampler.seed == 3
    older = ShardDataModule(runs.root / "data" / "train", runs.root / "data" / "val")
    older.load_state_dict({})  # a checkpoint of an older version: each epoch starts at its first batch
    assert older.resume is None


# -------------------------------------------------------------------------------------------- (c) validation


@pytest.mark.slow
def test_validation_metrics_are_the_whole_val_sets(runs):
    """Issue 34.1(c): the val metrics 2 processes log (5 samples: shares of 3 and 2, none repeated) equal those of
    one process on the same weights, at every validation."""
    single, two = _scalars(runs.single), _scalars(runs.two)
    val = {key: value for key, value in single.items() if key[0].startswith("val/") and "loss" not in key[0]}
    compared = [key for key in val if key in two]
    assert {step for _, step in compared} >= {1, 3, 7}  # validations after steps 2, 4, 8 (TensorBoard's step - 1)
    for key in compared:
        assert two[key] == pytest.approx(val[key], rel=1e-4, abs=1e-5), key


# ------------------------------------------------------------------------------- (d) rank 0 writes, resume


@pytest.mark.slow
def test_only_rank_zero_writes_and_the_resume_continues_the_step_count(runs):
    """Issue 34.1(d): one best checkpoint and last.ckpt, one TensorBoard event file per launch, one BEV image per
    validation, one export said once; the resumed run started at the stopped step and ended at the last."""
    checkpoints = sorted(path.name for path in (runs.two / "checkpoints").iterdir())
    assert len(checkpoints) == 2 and "last.ckpt" in checkpoints and checkpoints[0].startswith("best-")
    assert len(list((runs.two / "tensorboard").rglob("events.out.tfevents.*"))) == 2  # two launches
    images = sorted(path.name for path in (runs.two / "bev").iterdir())
    assert images == sorted(set(images)) and len(images) >= 3
    exported = sorted(path.name for path in (runs.two / "export").iterdir())  # the recipe's int8 network with the ONNX
    assert exported == ["fastflow3d.int8.onnx", "fastflow3d.onnx", "metadata.json"]
    said = "".join(result.stderr for result in runs.resumed)
    assert said.count("training: exported ") == 1
    assert said.count("training: effective batch 2 = 1 per device x 1 accumulated x 2 device(s) x 1 node(s)") == 1
    records = _records(runs.two)
    resumed_steps = [r["step"] for r in records[0] if r["pid"] != records[0][0]["pid"]]
    assert resumed_steps == list(range(runs.stopped_step, STEPS))
    assert _weights(runs.two)["global_step"] == STEPS


# -------------------------------------------------------------------------------------------------- (e) SIGTERM


@pytest.mark.slow
def test_sigterm_to_the_launcher_stops_every_rank_at_one_step_saved_once(runs):
    """Issue 34.1(e): SIGTERM to the launching process (before step 5) lets the step finish on both ranks, saves
    last.ckpt at that step once, says so in one line, exits 143 and leaves no process."""
    lines = [line for line in runs.stopped.stderr.splitlines() if line.startswith("train:")]
    assert lines == [
        f"train: terminated (SIGTERM) at step 6: saved {runs.two / 'checkpoints' / 'last.ckpt'}; to resume, rerun "
        "the same command with ckpt_path=last"
    ], runs.stopped.stderr[-3000:]
    assert runs.stopped_step == 6
    records = _records(runs.two)
    first = {rank: records[rank][0]["pid"] for rank in (0, 1)}
    assert first[0] != first[1]
    for rank in (0, 1):
        assert max(r["step"] for r in records[rank] if r["pid"] == first[rank]) == 5
        assert not _alive(first[rank])


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.mark.slow
def test_no_process_of_any_run_is_left(runs):
    records = [r for out in (runs.two, runs.elastic) for rank in _records(out).values() for r in rank]
    pids = {record["pid"] for record in records}
    assert len(pids) == 6 and not [pid for pid in pids if _alive(pid)]  # 3 launches x 2 ranks


# ------------------------------------------------------------------------------------------- cluster launches


SLURM_NODE_1 = {  # task 3 of 4: 2 nodes x 2 tasks, on the second node (what srun sets)
    "SLURM_JOB_ID": "4242",
    "SLURM_JOB_NAME": "train",
    "SLURM_NTASKS": "4",
    "SLURM_NTASKS_PER_NODE": "2",
    "SLURM_NNODES": "2",
    "SLURM_NODEID": "1",
    "SLURM_PROCID": "3",
    "SLURM_LOCALID": "1",
    "SLURM_NODELIST": "gpu[07-08]",
}
TORCHRUN_NODE_1 = {  # worker 3 of 4: torchrun --nnodes=2 --nproc_per_node=2 on the second node
    "TORCHELASTIC_RUN_ID": "job",
    "RANK": "3",
    "LOCAL_RANK": "1",
    "GROUP_RANK": "1",
    "WORLD_SIZE": "4",
    "LOCAL_WORLD_SIZE": "2",
    "MASTER_ADDR": "gpu07",
    "MASTER_PORT": "29500",
}


@pytest.mark.parametrize("launcher", ["slurm", "torchrun"])
def test_a_two_node_launch_is_read_from_the_launchers_variables(launcher, monkeypatch, tmp_path):
    """Issue 34.2: what a 2-node job's task sees (the variables srun or torchrun set; simulated): Lightning's
    cluster environment of that launcher, world size 4, this task's rank and node, an effective batch over both
    nodes, and not the launching process (which alone takes the run folder's lock and reports a stop)."""
    from lightning.fabric.plugins.environments import SLURMEnvironment, TorchElasticEnvironment

    from fastflow3d.training.trainer import build_trainer, settle_batch
    from icpflow.core.errors_and_signals import launching_process

    from helpers.training import compose_train

    for name in [*SLURM_NODE_1, *TORCHRUN_NODE_1, "NODE_RANK"]:
        monkeypatch.delenv(name, raising=False)
    for name, value in (SLURM_NODE_1 if launcher == "slurm" else TORCHRUN_NODE_1).items():
        monkeypatch.setenv(name, value)
    cfg = compose_train("trainer=ddp_cpu", "trainer.num_nodes=2", f"out_dir={tmp_path}", "~logger", "~callbacks")
    trainer = build_trainer(cfg)
    environment = {"slurm": SLURMEnvironment, "torchrun": TorchElasticEnvironment}[launcher]
    assert isinstance(trainer.strategy.cluster_environment, environment)
    if launcher == "slurm":  # a stop is train.py's (SIGTERM: last.ckpt), a resume ckpt_path=auto: not Lightning's
        assert trainer.strategy.cluster_environment.auto_requeue is False
    assert (trainer.world_size, trainer.global_rank, trainer.local_rank, trainer.node_rank) == (4, 3, 1, 1)
    batch = int(cfg.data.batch_size)
    assert settle_batch(cfg, trainer) == (
        batch * 4,
        f"effective batch {batch * 4} = {batch} per device x 1 accumulated x 2 device(s) x 2 node(s)",
    )
    assert not launching_process()


def test_the_slurm_sweep_launcher_asks_for_the_trainers_nodes_and_devices():
    """Issue 34.2: ``train.py -m hydra/launcher=slurm_ddp``: each job asks SLURM for trainer.num_nodes nodes and
    trainer.devices tasks and GPUs per node (hydra-submitit-launcher's SLURM launcher)."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from helpers.training import CONF

    overrides = ["hydra/launcher=slurm_ddp", "trainer=ddp", "trainer.devices=4", "trainer.num_nodes=2"]
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        cfg = compose("train", overrides, return_hydra_config=True)
    launcher = cfg.hydra.launcher
    assert launcher._target_.endswith("submitit_launcher.SlurmLauncher")
    assert [OmegaConf.select(cfg, f"hydra.launcher.{key}") for key in ("nodes", "tasks_per_node", "gpus_per_node")] == [
        2,
        4,
        4,
    ]
