import numpy as np

from icpflow.core.frame_pair import FramePair
from icpflow.core.geometry import ego_flow, make_transform
from icpflow.evaluation.baselines import ego_only_flow, zero_flow
from icpflow.evaluation.metrics import pair_stats


def _pair():
    rng = np.random.default_rng(0)
    pc0 = rng.uniform(-20, 20, (200, 3)).astype(np.float32)
    ego = make_transform(yaw=0.02, translation=(1.0, 0.1, 0.0))
    flow = ego_flow(pc0, ego).astype(np.float32)
    flow[:20] += np.array([1.0, 0.0, 0.0], np.float32)  # 20 moving points
    classes = np.zeros(200, np.int32)
    classes[:30] = 1
    return FramePair(pc0=pc0, pc1=pc0, ego1_from_ego0=ego, flow=flow, classes=classes)


def test_zero_flow_epe_is_gt_norm():
    pair = _pair()
    pred = zero_flow(pair)
    assert pred.shape == (200, 3) and pred.dtype == np.float32 and not pred.any()
    stats = pair_stats(pair.pc0, pred, pair.flow, pair.ego1_from_ego0, pair.classes, crop=None)
    np.testing.assert_allclose(stats["overall"][0] / 200, np.linalg.norm(pair.flow, axis=1).mean(), rtol=1e-6)


def test_ego_flow_zero_on_static_points():
    pair = _pair()
    pred = ego_only_flow(pair)
    assert pred.dtype == np.float32
    stats = pair_stats(pair.pc0, pred, pair.flow, pair.ego1_from_ego0, pair.classes, crop=None)
    assert stats["static_bg"][4] == 170 and stats["static_fg"][4] == 10
    assert stats["static_bg"][0] < 1e-4 and stats["static_fg"][0] < 1e-5
    np.testing.assert_allclose(stats["dynamic_fg"][0] / 20, 1.0, atol=1e-5)
