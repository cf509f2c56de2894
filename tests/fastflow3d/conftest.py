"""The tiny exported model the student wing's tests share, built once per test run (one pytest-xdist worker builds
each file, the others wait for it: ``built_once``): the tiny FastFlow3D of the
tests (helpers.training.TINY_MODEL: +-16 m, 1 m cells, 32 x 32 grid) trained a few steps on a synthetic pair so that
its weights and BatchNorm statistics are not the initial ones, saved as a training checkpoint (the checkpoint contract
of ``fastflow3d.artifact.checkpoint``), exported (ONNX, .pt2; with an int8 network; an older ground-removal version).
Tests read these files and never change them."""

from pathlib import Path

import numpy as np
import pytest
import torch
from filelock import FileLock

from fastflow3d.artifact.checkpoint import load_student
from fastflow3d.artifact.export import export_checkpoint
from fastflow3d.artifact.file_format import SingleSampleNet
from fastflow3d.inference.predictor import Predictor
from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.scans.ground import GroundSegmenter
from icpflow.scans.odometry import estimate_ego_motion
from icpflow.teacher.config import ICPFlowConfig

from helpers.exports import LEGACY_TEACHER, NEAR, eager_full_flow
from helpers.students import tiny_checkpoint  # tests/ is on sys.path (pytest prepend import mode)


def built_once(tmp_path_factory, worker_id: str, name: str, build) -> Path:
    """The path ``build(folder)`` returns, made once per test run in a folder of its own: in one process, a fresh
    folder; under pytest-xdist, the run's shared temporary folder (each run has its own), where the first worker to
    ask builds it under a lock and the others wait, then read the path it wrote."""
    if worker_id == "master":
        return build(tmp_path_factory.mktemp(name))
    folder = tmp_path_factory.getbasetemp().parent / name
    done = folder / "built"
    with FileLock(f"{folder}.lock"):
        if not done.exists():
            folder.mkdir(exist_ok=True)
            done.write_text(str(build(folder)))
    return Path(done.read_text())


@pytest.fixture(scope="session")
def pairs():
    """Synthetic pairs with different point counts: a whole pair and two random subsets of the next one."""
    dataset = SyntheticDataset(split="test", beams=32, num_sequences=1, frames_per_sequence=3, seed=0)
    whole, other = dataset[0], dataset[1]
    rng = np.random.default_rng(0)
    subsets = []
    for n0, n1 in [(9000, 31000), (20000, 700)]:
        keep0, keep1 = rng.choice(len(other.pc0), n0, replace=False), rng.choice(len(other.pc1), n1, replace=False)
        subsets.append(
            other.replace(
                pc0=other.pc0[keep0],
                pc1=other.pc1[keep1],
                flow=other.flow[keep0],
                ground0=None,
                ground1=None,
                flow_valid=None,
                classes=None,
                instance=None,
                dynamic=None,
            )
        )
    return [whole, *subsets]


@pytest.fixture(scope="session")
def checkpoint(tmp_path_factory, worker_id, pairs):
    """A training checkpoint of the tiny model after 15 Adam steps towards one pair's true residual flow (on 6000
    points of each scan near the grid, to keep it fast)."""
    pair = pairs[0]
    near0 = np.flatnonzero(np.abs(pair.pc0[:, :2]).max(axis=1) < NEAR)[:6000]
    near1 = np.flatnonzero(np.abs(pair.pc1[:, :2]).max(axis=1) < NEAR)[:6000]
    return built_once(
        tmp_path_factory, worker_id, "run", lambda folder: tiny_checkpoint(folder / "best.ckpt", pair, 15, near0, near1)
    )


@pytest.fixture(scope="session")
def export_dir(tmp_path_factory, worker_id, checkpoint):
    return built_once(tmp_path_factory, worker_id, "export", lambda _: export_checkpoint(checkpoint))


@pytest.fixture(scope="session")
def eager(checkpoint):
    """The trained tiny network in eval mode, from the checkpoint."""
    return SingleSampleNet(load_student(checkpoint)[0]).eval()


@pytest.fixture(scope="session")
def expected(eager, pairs):
    """Eager full flow and in-grid mask of every pair (given ego motion)."""
    return [eager_full_flow(eager, pair) for pair in pairs]


@pytest.fixture(scope="session")
def teacher_ego(pairs, export_dir):
    """The teacher's ego-motion estimate (step 1, default settings: the odometry of the two scans without their
    ground's surface, found with the model's settings) of the smallest pair."""
    pair = pairs[1]
    segmenter = GroundSegmenter(Predictor.load(export_dir).preprocessing)
    surface0, surface1 = segmenter.masks(pair.pc0)[1], segmenter.masks(pair.pc1)[1]
    return estimate_ego_motion(pair.pc0, pair.pc1, ICPFlowConfig(), surface0, surface1)


@pytest.fixture(scope="session")
def ground_checkpoint(tmp_path_factory, worker_id, checkpoint):
    """The same trained weights in a checkpoint of an older version whose config says the network saw non-ground
    points only, with the teacher settings of the synthetic dataset (a 1.9 m high sensor over a z = 0 ground) as a
    flat ``data.teacher`` dict (before the typed preprocessing block)."""
    teacher = ICPFlowConfig.preset(
        "waymo", ground={"method": "both", "sensor_height": 1.9, "patchwork_z_offset": -1.9}
    )  # the ground of that version, as its flat dict says

    def build(folder: Path) -> Path:
        saved = torch.load(checkpoint, weights_only=True)
        del saved["hyper_parameters"]["cfg"]["input"]  # older versions stored no input contract
        saved["hyper_parameters"]["cfg"]["data"] = {"remove_ground": True, "teacher": dict(LEGACY_TEACHER)}
        torch.save(saved, folder / "best.ckpt")
        return folder / "best.ckpt"

    return built_once(tmp_path_factory, worker_id, "ground", build), teacher


@pytest.fixture(scope="session")
def ground_export(tmp_path_factory, worker_id, ground_checkpoint):
    """The ground-removal checkpoint exported (pt2 only)."""
    return built_once(
        tmp_path_factory,
        worker_id,
        "ground_export",
        lambda _: export_checkpoint(ground_checkpoint[0], formats=("pt2",)),
    )


# ------------------------------------------------------------------------------------------- the int8 network
@pytest.fixture(scope="session")
def int8_export(tmp_path_factory, worker_id, checkpoint):
    """The tiny checkpoint exported as ONNX with its int8 network, calibrated on the run's training shards."""
    return built_once(
        tmp_path_factory,
        worker_id,
        "int8",
        lambda folder: export_checkpoint(checkpoint, folder / "export", formats=("onnx",), int8=True),
    )
