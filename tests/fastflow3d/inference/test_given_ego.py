"""A given ego motion is checked cheaply, and one that cannot be estimated is said to be assumed (issue 31,
point 4)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fastflow3d.artifact.export import export_model
from fastflow3d.inference.prediction import PredictorWarning
from fastflow3d.inference.predictor import Predictor
from icpflow.core.geometry import invert
from icpflow.datasets.synthetic.reader import SyntheticDataset

from helpers.students import tiny_network  # tests/ is on sys.path (pytest prepend import mode)
from helpers.training import TINY_MODEL


@pytest.fixture(scope="module")
def predictor(tmp_path_factory):
    torch.manual_seed(0)
    out = tmp_path_factory.mktemp("export") / "export"
    export_model(tiny_network(), out, ("pt2",), model_config=TINY_MODEL)
    return out


@pytest.fixture(scope="module")
def pair():
    dataset = SyntheticDataset(split="test", beams=32, num_sequences=1, frames_per_sequence=2, seed=4)
    pair = dataset[0]
    assert np.linalg.norm(pair.ego1_from_ego0[:3, 3]) > 0.5  # the ego moves: an inverted transform is far off
    return pair


def test_the_true_ego_motion_passes_and_its_inverse_is_flagged(predictor, pair, recwarn):
    model = Predictor.load(predictor)
    model(pair.pc0, pair.pc1, pair.ego1_from_ego0)
    assert not [w for w in recwarn if issubclass(w.category, PredictorWarning)]
    with pytest.warns(PredictorWarning, match="the given ego1_from_ego0 fits the scans worse than its inverse"):
        model(pair.pc0, pair.pc1, invert(pair.ego1_from_ego0))
    recwarn.clear()
    model(pair.pc0, pair.pc1, invert(pair.ego1_from_ego0))  # a warning ends the checks: said once
    assert not [w for w in recwarn if issubclass(w.category, PredictorWarning)] and model.ego_checks_left == 0


def test_too_few_points_is_said_and_marked_assumed(predictor, pair):
    model = Predictor.load(predictor)
    with pytest.warns(PredictorWarning, match=r"too few points to estimate the ego motion \(pc0 50, pc1 60"):
        prediction = model.predict(pair.pc0[:50], pair.pc1[:60])
    assert prediction.ego_assumed and not prediction.ego_estimated
    np.testing.assert_array_equal(prediction.ego1_from_ego0, np.eye(4))


def test_the_height_frame_warning_is_said_once_per_predictor(predictor, pair):
    import warnings

    model = Predictor.load(predictor)
    lowered0, lowered1 = pair.pc0 - np.float32([0, 0, 1.7]), pair.pc1 - np.float32([0, 0, 1.7])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for _ in range(3):
            model(lowered0, lowered1, pair.ego1_from_ego0)
    said = [w for w in caught if issubclass(w.category, PredictorWarning) and "lifted by" in str(w.message)]
    assert len(said) == 1 and "said once" in str(said[0].message)
