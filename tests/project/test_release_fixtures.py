"""Nothing changes for users (issue 32.5): what the previous release wrote (``tests/fixtures/release_0_1``, made by
``tests/fixtures/make_release_fixtures.py`` with that release's code: a label folder, a training checkpoint and its
export) loads with today's code and gives the same flow, and today's input contract reads each stored form the same
way."""

from __future__ import annotations

import numpy as np
import pytest

from fastflow3d.inference.predictor import Predictor
from icpflow.datasets.synthetic.reader import SyntheticDataset

from helpers.data import REPO

FIXTURES = REPO / "tests" / "fixtures" / "release_0_1"


@pytest.fixture(scope="module")
def pair():
    return SyntheticDataset(
        split="train", num_sequences=1, frames_per_sequence=2, beams=32, azimuth_resolution_deg=2.0
    )[0]


@pytest.mark.parametrize(
    "name, path, backend",
    [("checkpoint", "checkpoint/last.ckpt", None), ("onnx", "export", "onnx"), ("pt2", "export", "pt2")],
)
def test_a_stored_model_of_the_previous_release_gives_the_same_flow(pair, name, path, backend):
    predictor = Predictor.load(FIXTURES / path, backend=backend)
    flow = predictor.predict(pair.pc0, pair.pc1, pair.ego1_from_ego0).flow
    np.testing.assert_allclose(flow, np.load(FIXTURES / f"flow_{name}.npy"), atol=1e-5)


def test_the_stored_forms_of_the_previous_release_read_as_one_contract():
    """The shards' labeller block, the checkpoint's config and the export's metadata of one run: one contract (the
    shards carry no grid or ground-removal choice: those come from the training run)."""
    import json

    import torch

    from fastflow3d.network.contract import upgrade
    from fastflow3d.training.data import labeller_contract

    checkpoint = torch.load(FIXTURES / "checkpoint" / "last.ckpt", weights_only=True, map_location="cpu")
    from_checkpoint = upgrade(checkpoint["hyper_parameters"]["cfg"])
    from_export = upgrade(json.loads((FIXTURES / "export" / "metadata.json").read_text()))
    assert from_checkpoint == from_export
    assert from_export.remove_ground and from_export.grid.cell == 1.0
    assert labeller_contract(FIXTURES / "labels", True, from_export.grid) == from_export


def test_the_stored_config_names_todays_targets():
    """The checkpoint's config names its classes by the paths of the code that wrote it (``fastflow3d.model...``);
    read through ``read_checkpoint``, each ``_target_`` is today's path (``MOVED_TARGETS``) and imports."""
    import torch
    from hydra.utils import get_object

    from fastflow3d.artifact.checkpoint import MOVED_TARGETS, read_checkpoint

    def targets(node):
        if isinstance(node, dict):
            return [value for key, value in node.items() if key == "_target_"] + sum(map(targets, node.values()), [])
        return sum(map(targets, node), []) if isinstance(node, list) else []

    stored = torch.load(FIXTURES / "checkpoint" / "last.ckpt", weights_only=True, map_location="cpu")
    stored = stored["hyper_parameters"]["cfg"]
    assert stored["model"]["_target_"] == "fastflow3d.model.FastFlow3D"  # as the previous release wrote it
    read = read_checkpoint(FIXTURES / "checkpoint" / "last.ckpt")["hyper_parameters"]["cfg"]
    assert read["model"]["_target_"] == "fastflow3d.network.model.FastFlow3D"
    assert len(targets(read)) == len(targets(stored)) >= 4
    for target in targets(read):
        assert target.rpartition(".")[0] not in MOVED_TARGETS
        get_object(target)
