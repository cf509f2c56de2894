"""The student's input contract (fastflow3d.network.contract): the rows the network sees, the way back to the input
rows, and every stored form read by one function."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fastflow3d.network.contract import VERSION, ContractError, InputContract, upgrade
from fastflow3d.network.model import compensate
from fastflow3d.network.voxelize import Grid
from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.scans.preprocess import HeightFrame, Preprocessing
from icpflow.teacher.config import ICPFlowConfig

GRID = Grid((-8.0, 8.0), (-8.0, 8.0), (-1.0, 3.0), 0.5)


@pytest.fixture(scope="module")
def pair():
    return SyntheticDataset(split="val", num_sequences=1, frames_per_sequence=2, beams=32, seed=3)[0]


@pytest.mark.parametrize("remove_ground", [True, False])
def test_prepare_hands_the_network_the_compensated_rows_inside_the_grid_off_the_ground(pair, remove_ground):
    contract = InputContract(remove_ground=remove_ground, grid=GRID)
    prepared = contract.prepare(pair.pc0, pair.pc1, pair.ego1_from_ego0, pair.ground0, pair.ground1)
    compensated = compensate(pair.pc0, pair.ego1_from_ego0)
    np.testing.assert_array_equal(prepared.compensated, compensated)

    def inside(points):
        cells = np.floor((points[:, :2] - np.float32([-8.0, -8.0])) / np.float32(0.5))
        return (cells >= 0).all(1) & (cells < 32).all(1) & (points[:, 2] >= -1.0) & (points[:, 2] <= 3.0)

    expected0 = inside(compensated) & (~pair.ground0 if remove_ground else True)
    expected1 = inside(pair.pc1) & (~pair.ground1 if remove_ground else True)
    np.testing.assert_array_equal(prepared.rows0, np.flatnonzero(expected0))
    np.testing.assert_array_equal(prepared.rows1, np.flatnonzero(expected1))
    assert 0 < len(prepared.rows0) < len(pair.pc0) and prepared.network0.flags["C_CONTIGUOUS"]
    np.testing.assert_array_equal(prepared.network1, pair.pc1[expected1])
    # the same test on a flat torch batch (training, validation) gives the same rows
    mask = contract.network_mask(torch.from_numpy(compensated), torch.from_numpy(pair.ground0))
    np.testing.assert_array_equal(mask.numpy(), expected0)


def test_restore_puts_the_residual_back_on_the_input_rows(pair):
    contract = InputContract(remove_ground=True, grid=GRID)
    prepared = contract.prepare(pair.pc0, pair.pc1, pair.ego1_from_ego0, pair.ground0, pair.ground1)
    rng = np.random.default_rng(0)
    residual = rng.normal(size=(len(prepared.rows0), 3)).astype(np.float32)
    valid = rng.random(len(prepared.rows0)) > 0.2
    full, in_grid = contract.restore(prepared, residual, valid)
    assert full.shape == (len(pair.pc0), 3) and full.dtype == np.float32
    np.testing.assert_array_equal(np.flatnonzero(in_grid), prepared.rows0[valid])
    np.testing.assert_array_equal(full[prepared.rows0[valid]], residual[valid])
    assert not full[~in_grid].any()


def test_a_lift_raises_both_scans_and_keeps_every_row(pair):
    """Scans 1.9 m below the model's frame (a sensor frame) lifted back: the same rows and compensated points."""
    contract = InputContract(remove_ground=True, grid=GRID)
    down = np.float32([0, 0, 1.9])
    from icpflow.scans.preprocess import lift_transform

    ego = lift_transform(pair.ego1_from_ego0, -1.9)
    lifted = contract.prepare(pair.pc0 - down, pair.pc1 - down, ego, pair.ground0, pair.ground1, lift=1.9)
    direct = contract.prepare(pair.pc0, pair.pc1, pair.ego1_from_ego0, pair.ground0, pair.ground1)
    np.testing.assert_array_equal(lifted.rows0, direct.rows0)
    np.testing.assert_array_equal(lifted.rows1, direct.rows1)
    np.testing.assert_allclose(lifted.compensated, direct.compensated, atol=1e-5)


def test_every_stored_form_reads_as_one_contract():
    teacher = ICPFlowConfig.preset("av2", ground={"sensor_height": 1.5})
    preprocessing = Preprocessing.from_teacher(teacher)
    contract = InputContract(preprocessing, True, GRID)
    stored = contract.to_dict()
    assert stored["version"] == VERSION and "patchwork_z_offset" not in stored["ground"]  # derived, never stored
    grid = {"x_range": [-8.0, 8.0], "y_range": [-8.0, 8.0], "z_range": [-1.0, 3.0], "cell": 0.5}
    forms = {
        "this version": stored,
        "in an export's metadata": {"metadata_version": 2, "input": stored},
        "in a checkpoint's config": {"model": {"_target_": "x", **grid}, "input": stored},
        "export metadata v1": {
            "metadata_version": 1,
            "grid": {**grid, "nx": 32, "ny": 32},
            "preprocessing": {"remove_ground": True, **preprocessing.to_dict()},
        },
        "checkpoint config v1": {
            "model": grid,
            "data": {"remove_ground": True, "preprocessing": preprocessing.to_dict()},
        },
    }
    for name, form in forms.items():
        assert upgrade(form) == contract, name
    shards = {"split": "train", "preprocessing": preprocessing.to_dict(), "teacher": teacher.to_dict()}
    assert upgrade(shards, remove_ground=True, grid=GRID) == contract
    # the oldest exports: no preprocessing entry, trained on every point in the synthetic frame
    oldest = upgrade({"metadata_version": 1, "grid": grid})
    assert not oldest.remove_ground and oldest.preprocessing.frame == HeightFrame(0.0)


@pytest.mark.parametrize(
    "form, words",
    [
        ({**InputContract().to_dict(), "version": VERSION + 1}, "newer than this code's"),
        ({"input": {**InputContract().to_dict(), "version": 1}}, "is not 2"),
        ({"input": "yes"}, "must be a mapping"),
        ({"split": "train", "preprocessing": {}}, "says nothing about ground removal"),
        ({**InputContract().to_dict(), "grid": {"cell": -1}}, "grid"),
        ({**InputContract().to_dict(), "ground": {"method": "sometimes"}}, "method"),
    ],
)
def test_a_stored_form_that_cannot_be_read_is_one_line(form, words):
    with pytest.raises(ContractError, match=words) as caught:
        upgrade(form)
    assert "\n" not in str(caught.value)
