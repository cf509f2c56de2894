"""The student's training recipe: step schedules, augmentation that keeps every target exact, the norm choice."""

import numpy as np
import pytest
import torch

from fastflow3d.training.augment import Augmentation, subsample, transform_sample
from fastflow3d.training.schedules import warmup_cosine, warmup_multistep
from icpflow.core.geometry import full_to_residual, transform_points
from icpflow.datasets.synthetic.reader import SyntheticDataset

from helpers.shards import write_labels
from helpers.students import tiny_network


def _lrs(make, total: int) -> list[float]:
    optimiser = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=1.0)
    schedule = make(optimiser, total)
    lrs = []
    for _ in range(total):
        lrs.append(optimiser.param_groups[0]["lr"])
        optimiser.step()
        schedule.step()
    return lrs


def test_warmup_cosine_shape():
    lrs = _lrs(lambda o, n: warmup_cosine(o, n, warmup_steps=10, final_factor=0.01), 110)
    assert lrs[0] == pytest.approx(1 / 11) and lrs[9] == pytest.approx(10 / 11) and lrs[10] == pytest.approx(1.0)
    assert lrs[60] == pytest.approx(0.01 + 0.99 * 0.5)  # half way through the decay
    assert all(a >= b for a, b in zip(lrs[10:], lrs[11:])) and lrs[-1] == pytest.approx(0.01, abs=1e-3)
    # a run shorter than the warm-up warms up over half of it, then decays
    short = _lrs(lambda o, n: warmup_cosine(o, n, warmup_steps=100), 8)
    assert short[3] == pytest.approx(0.8) and short[4] == pytest.approx(1.0) and short[-1] < short[4]


def test_warmup_multistep_milestones_are_fractions_of_the_run():
    lrs = _lrs(lambda o, n: warmup_multistep(o, n, milestones=(0.5,), gamma=0.1), 40)
    assert lrs[19] == pytest.approx(1.0) and lrs[20] == pytest.approx(0.1) and lrs[-1] == pytest.approx(0.1)
    # the same fraction on a 4x longer run: the drop moves with the run, not with the dataset size
    assert _lrs(lambda o, n: warmup_multistep(o, n, milestones=(0.5,)), 160)[80] == pytest.approx(0.1)
    with pytest.raises(ValueError, match="fractions"):
        warmup_multistep(torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=1.0), 10, milestones=(25,))


@pytest.fixture(scope="module")
def sample():
    """A shard-like numpy sample (pseudo flow = ground truth) from the synthetic world, with moving objects."""
    pair = SyntheticDataset(
        split="train", num_sequences=1, frames_per_sequence=2, beams=32, azimuth_resolution_deg=1.0
    ).pair(0)
    assert pair.dynamic.any()
    n0 = len(pair.pc0)
    return {
        "pc0": pair.pc0,
        "pc1": pair.pc1,
        "ego1_from_ego0": pair.ego1_from_ego0,
        "flow": pair.flow,
        "gt_flow": pair.flow,
        "gt_flow_valid": pair.flow_valid,
        "gt_classes": pair.classes,
        "ground0": pair.ground0,
        "ground1": pair.ground1,
        "confidence": np.linspace(0, 1, n0, dtype=np.float32),
        "cluster": np.arange(n0, dtype=np.int32),
        "dt": pair.dt,
        "sample_id": pair.sample_id,
    }


@pytest.mark.parametrize("seed", range(4))
def test_augmentation_moves_scans_flows_and_ego_motion_together(sample, seed):
    """After a random yaw / mirror / height shift, pc0 + flow is still each point's position at t + dt in the
    (transformed) ego frame of t + dt, the ego motion is a proper rigid transform, static points (residual 0) stay
    static and the residual flow is the rotated residual."""
    transform = Augmentation(yaw_deg=180.0, flip=True, height_shift=0.3, keep_min=1.0).draw(np.random.default_rng(seed))
    moved = transform_sample(sample, transform)
    np.testing.assert_allclose(
        moved["pc0"] + moved["flow"], transform_points(transform, sample["pc0"] + sample["flow"]), atol=2e-4
    )
    np.testing.assert_allclose(moved["pc1"], transform_points(transform, sample["pc1"]), atol=1e-4)
    ego = moved["ego1_from_ego0"]
    assert np.linalg.det(ego[:3, :3]) == pytest.approx(1.0) and np.allclose(ego[:3, :3] @ ego[:3, :3].T, np.eye(3))
    residual = full_to_residual(sample["flow"], sample["pc0"], sample["ego1_from_ego0"])
    moved_residual = full_to_residual(moved["flow"], moved["pc0"], ego)
    np.testing.assert_allclose(moved_residual, residual @ transform[:3, :3].T, atol=2e-4)
    assert np.abs(moved_residual[np.linalg.norm(residual, axis=1) == 0]).max() < 2e-4
    np.testing.assert_array_equal(moved["ground0"], sample["ground0"])


def test_mirror_flips_y_and_keeps_the_ego_motion_rigid(sample):
    mirror = np.diag([1.0, -1.0, 1.0, 1.0])
    moved = transform_sample(sample, mirror)
    np.testing.assert_allclose(moved["pc0"][:, 1], -sample["pc0"][:, 1])
    np.testing.assert_allclose(moved["flow"][:, 1], -sample["flow"][:, 1])
    assert np.linalg.det(moved["ego1_from_ego0"][:3, :3]) == pytest.approx(1.0)


def test_subsampling_keeps_per_point_values_aligned(sample):
    kept = subsample(sample, np.random.default_rng(0), keep_min=0.5)
    assert 0.5 * len(sample["pc0"]) - 1 <= len(kept["pc0"]) < len(sample["pc0"])
    rows = kept["cluster"]  # cluster holds the row number of each point in this fixture
    for key in ("pc0", "flow", "gt_flow", "gt_classes", "ground0", "confidence"):
        np.testing.assert_array_equal(kept[key], sample[key][rows])
    assert len(kept["ground1"]) == len(kept["pc1"]) <= len(sample["pc1"])
    assert subsample(sample, np.random.default_rng(0), keep_min=1.0) is sample
    with pytest.raises(ValueError, match="keep_min"):
        Augmentation(keep_min=0.0)


def test_training_dataset_augments_and_validation_does_not(tmp_path, sample):
    """StudentDataset with an Augmentation draws a new transform per read (torch's random state); without, reads
    are identical. The residual target stays consistent with the ego motion either way."""
    from fastflow3d.training.data import StudentDataset

    stored = {
        key: sample[key]
        for key in ("pc0", "pc1", "ego1_from_ego0", "flow", "ground0", "ground1", "confidence", "cluster")
    }
    stored["attrs"] = {
        "sample_id": "s",
        "log_id": "l",
        "index": 0,
        "timestamp0_ns": -1,
        "timestamp1_ns": -1,
        "dt": sample["dt"],
    }
    write_labels(tmp_path, {"shard_000000.h5": [stored]}, "{}", "test")
    plain = StudentDataset(tmp_path)
    torch.manual_seed(0)  # the state that draws the augmented transforms below
    read = plain[0]  # validation: exactly the stored points and residual target
    assert torch.equal(read["pc0"], torch.from_numpy(sample["pc0"]))
    residual = full_to_residual(sample["flow"], sample["pc0"], sample["ego1_from_ego0"])
    assert torch.equal(read["pseudo"], torch.from_numpy(residual))
    augmented = StudentDataset(tmp_path, Augmentation())
    torch.manual_seed(0)
    first, second = augmented[0], augmented[0]
    assert not torch.equal(first["pc0"][:100], second["pc0"][:100])
    for item in (first, second):  # residual target = rotated residual: its norm is unchanged per point
        assert float(item["pseudo"].norm(dim=1).max()) <= float(plain[0]["pseudo"].norm(dim=1).max()) * 1.001
        assert float(item["pseudo"].norm(dim=1).max()) > 0


def test_group_norm_student_trains_and_has_no_running_statistics():
    torch.manual_seed(0)
    model = tiny_network(norm="group")
    assert not any(isinstance(m, torch.nn.modules.batchnorm._BatchNorm) for m in model.modules())
    pc0, pc1 = torch.rand(500, 3) * 20 - 10, torch.rand(400, 3) * 20 - 10
    b0, b1 = torch.zeros(500, dtype=torch.long), torch.zeros(400, dtype=torch.long)
    residual, valid = model(pc0, b0, pc1, b1, 1)
    residual.square().sum().backward()
    assert all(p.grad is not None for p in model.parameters())
    with torch.no_grad():  # no running statistics: train and eval mode compute the same function
        torch.testing.assert_close(model.eval()(pc0, b0, pc1, b1, 1)[0], model.train()(pc0, b0, pc1, b1, 1)[0])
    with pytest.raises(ValueError, match="norm must be one of"):
        tiny_network(norm="layer")
