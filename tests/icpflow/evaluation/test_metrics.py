import numpy as np
import pytest

from icpflow.core.frame_pair import FramePair
from icpflow.core.geometry import ego_flow, make_transform
from icpflow.core.open3d_loader import provide_libusb
from icpflow.evaluation.metrics import (
    AV2_META,
    META_CLASSES,
    THREEWAY_EDGES,
    THREEWAY_META,
    MetricAccumulator,
    av2_bucket_stats,
    bucketed_epe,
    format_table,
    frame_pair_stats,
    pair_stats,
    threeway_epe,
)

from helpers.data import needs_shared, shared

I4 = np.eye(4)


def _case():
    # 5 points, identity ego motion; dt 0.1 so dynamic = |gt| > 0.05 m.
    pc0 = np.array([[1, 0, 0], [2, 0, 0], [3, 0, 0], [4, 0, 0], [40, 0, 0]], np.float32)
    gt = np.array([[1.0, 0, 0], [0, 0, 0], [0, 0, 0], [2.0, 0, 0], [0, 0, 0]], np.float32)
    pred = gt.copy()
    pred[0, 0] += 0.06  # dynamic fg: EPE 0.06, rel 6 %: not AccS, AccR, no outlier
    pred[1, 1] += 0.049  # static fg: EPE 0.049: AccS, AccR, outlier (rel huge)
    pred[2, 2] += 0.5  # static bg: EPE 0.5: outlier
    pred[3, 0] += 0.25  # dynamic bg (class 0): only in overall; EPE 0.25 rel 12.5 % -> outlier
    classes = np.array([1, 2, 0, 0, 0], np.int32)
    return pc0, pred, gt, classes


def test_pair_stats_hand_case():
    pc0, pred, gt, classes = _case()
    s = pair_stats(pc0, pred, gt, I4, classes)
    np.testing.assert_allclose(s["dynamic_fg"], [0.06, 0, 1, 0, 1], atol=1e-6)
    np.testing.assert_allclose(s["static_fg"], [0.049, 1, 1, 1, 1], atol=1e-6)
    np.testing.assert_allclose(s["static_bg"], [0.5, 0, 0, 1, 1], atol=1e-6)
    np.testing.assert_allclose(s["overall"], [0.859, 1, 2, 3, 4], atol=1e-6)  # point at x=40 cropped


def test_crop_ground_valid_and_full_relative():
    pc0, pred, gt, classes = _case()
    s = pair_stats(pc0, pred, gt, I4, classes, crop=None)
    assert s["overall"][4] == 5 and s["static_bg"][4] == 2
    ground = np.array([0, 0, 1, 0, 0], bool)
    assert pair_stats(pc0, pred, gt, I4, classes, ground=ground)["static_bg"][4] == 0
    assert pair_stats(pc0, pred, gt, I4, classes, ground=ground, include_ground=True)["static_bg"][4] == 1
    ego = make_transform(translation=(1.0, 0.0, 0.0))  # static point 1: full |gt| 1 m, EPE 0.049 -> 4.9 %
    full = pair_stats(pc0, pred + ego_flow(pc0, ego), gt + ego_flow(pc0, ego), ego, classes, relative_to="full")
    np.testing.assert_allclose(full["static_fg"], [0.049, 1, 1, 0, 1], atol=1e-6)
    with pytest.raises(ValueError, match="classes has shape"):
        pair_stats(pc0, pred, gt, I4, classes[:4])
    valid = np.array([0, 1, 1, 1, 1], bool)
    assert pair_stats(pc0, pred, gt, I4, classes, flow_valid=valid)["dynamic_fg"][4] == 0


def test_ego_motion_residual_split():
    pc0, _, _, classes = _case()
    ego = make_transform(yaw=0.1, translation=(1.0, 0.0, 0.0))
    gt = ego_flow(pc0, ego)  # everything static although the full flow is about 1 m
    s = pair_stats(pc0, gt, gt, ego, classes)
    assert s["dynamic_fg"][4] == 0 and s["static_fg"][4] == 2 and s["overall"][0] == 0


def test_accumulator_both_aggregations_and_empty():
    pc0, pred, gt, classes = _case()
    acc = MetricAccumulator()
    acc.add(pair_stats(pc0, pred, gt, I4, classes))
    acc.add(pair_stats(pc0, gt, gt, I4, np.zeros(5, np.int32)))  # 2 static bg points (x=2, 3) with EPE 0
    t = acc.table()
    assert t["point_weighted"]["static_bg"]["count"] == 3
    assert t["point_weighted"]["static_bg"]["EPE"] == pytest.approx(0.5 / 3)
    assert t["per_pair"]["static_bg"]["EPE"] == pytest.approx(0.25)
    assert t["per_pair"]["dynamic_fg"]["count"] == 1
    empty = MetricAccumulator()
    empty.add(pair_stats(pc0, gt, gt, I4, np.zeros(5, np.int32)))
    row = empty.table()["point_weighted"]["dynamic_fg"]
    assert row["count"] == 0 and np.isnan(row["EPE"])
    text = format_table({"zero": t["point_weighted"]})
    assert text.splitlines()[2].startswith("zero") and "0.1667" in text


def test_frame_pair_entry_point():
    pc0, pred, gt, classes = _case()
    pair = FramePair(pc0=pc0, pc1=pc0, ego1_from_ego0=I4, flow=gt, classes=classes)
    expected = pair_stats(pc0, pred, gt, I4, classes)["overall"]
    np.testing.assert_allclose(frame_pair_stats(pair, pred)["overall"], expected)


def _random_av2(n=6000, seed=0):
    rng = np.random.default_rng(seed)
    pc0 = rng.uniform(-45, 45, (n, 3)).astype(np.float32)
    classes = rng.choice([0, 0, 0, 19, 17, 6, 4, 3, 1, 5, 21], n).astype(np.int32)  # includes unmapped ones
    ego = make_transform(yaw=0.01, translation=(0.8, 0.05, 0.0))
    speed = np.where(classes > 0, rng.uniform(0, 2.5, n), rng.uniform(0, 0.06, n))
    direction = rng.normal(size=(n, 3))
    residual = direction / np.linalg.norm(direction, axis=1, keepdims=True) * speed[:, None]
    gt = (residual + ego_flow(pc0, ego)).astype(np.float32)
    pred = (gt + rng.normal(0, 0.1, (n, 3))).astype(np.float32)
    ground = rng.random(n) < 0.2
    return pc0, pred, gt, ego, classes, ground


def _package_results(evaluator, frames):
    from bucketed_scene_flow_eval.datastructures import PointCloud

    for pc0, pred, gt, ego, classes, ground in frames:
        keep = ~ground
        e = ego_flow(pc0, ego)
        evaluator.eval_frame_results.append(
            evaluator._build_eval_frame_results(
                PointCloud(pc0[keep].astype(np.float64)),
                (classes[keep] - 1).astype(np.int8),
                (gt - e)[keep].astype(np.float64),
                (pred - e)[keep].astype(np.float64),
            )
        )
    return evaluator.compute_results(save_results=False)


def _package_mean(evaluator):
    """The package's mean over meta-classes (static EPE, dynamic normalised EPE), after ``_package_results``."""
    stats = evaluator._category_to_average_stats(evaluator._category_to_per_frame_stats())
    return evaluator._build_stat_table(stats, 35).get_mean_average_values().to_tuple()


def test_parity_with_bucketed_scene_flow_eval(tmp_path):
    provide_libusb()  # the package imports open3d itself
    pytest.importorskip("bucketed_scene_flow_eval", reason="bucketed-scene-flow-eval not installed")
    from bucketed_scene_flow_eval.datasets.argoverse2.argoverse_scene_flow import CATEGORY_MAP
    from bucketed_scene_flow_eval.datasets.argoverse2.av2_metacategories import (
        BUCKETED_METACATAGORIES,
        THREEWAY_EPE_METACATAGORIES,
    )
    from bucketed_scene_flow_eval.eval import BucketedEPEEvaluator, ThreeWayEPEEvaluator

    frames = [_random_av2(seed=s) for s in range(3)]
    ours = sum(av2_bucket_stats(*f[:5], ground=f[5]) for f in frames)
    evaluator = BucketedEPEEvaluator(
        CATEGORY_MAP, output_path=tmp_path / "b", meta_class_lookup=BUCKETED_METACATAGORIES
    )
    ref = _package_results(evaluator, frames)
    mine = bucketed_epe(ours)
    for meta in META_CLASSES:
        np.testing.assert_allclose(mine["per_class"][meta], ref[meta], atol=1e-6, rtol=0)
    np.testing.assert_allclose(mine["mean"], _package_mean(evaluator), atol=1e-6, rtol=0)
    ours3 = sum(
        av2_bucket_stats(
            *f[:5], ground=f[5], class_to_meta=THREEWAY_META, edges=THREEWAY_EDGES, metas=("BACKGROUND", "FOREGROUND")
        )
        for f in frames
    )
    ref3 = _package_results(
        ThreeWayEPEEvaluator(CATEGORY_MAP, THREEWAY_EPE_METACATAGORIES, output_path=tmp_path / "t"), frames
    )
    three = threeway_epe(ours3)
    np.testing.assert_allclose(
        [three["background_static"], three["foreground_static"], three["foreground_dynamic"]],
        [ref3["BACKGROUND"][0], ref3["FOREGROUND"][0], ref3["FOREGROUND"][1]],
        atol=1e-6,
    )


def test_bucketed_hand_case():
    # Two CAR points (class 19 = REGULAR_VEHICLE + 1): one static (EPE 0.1), one at 1.0 m/frame (EPE 0.5).
    pc0 = np.zeros((4, 3), np.float32)
    gt = np.array([[0, 0, 0], [1.0, 0, 0], [0, 0, 0], [0, 0.01, 0]], np.float32)
    pred = gt + np.array([[0.1, 0, 0], [0.5, 0, 0], [0, 0, 0.2], [0, 0, 0]], np.float32)
    classes = np.array([19, 19, 0, 10], np.int32)  # 10 = DOG: in no meta-class
    sums = av2_bucket_stats(pc0, pred, gt, I4, classes)
    assert sums[:, :, 2].sum() == 3 and sums[META_CLASSES.index("CAR"), 25, 2] == 1  # 1.0 in [1.0, 1.04)
    result = bucketed_epe(sums)
    assert result["per_class"]["CAR"] == pytest.approx((0.1, 0.5))
    assert result["per_class"]["BACKGROUND"][0] == pytest.approx(0.2)
    assert np.isnan(result["per_class"]["BACKGROUND"][1]) and np.isnan(result["per_class"]["PEDESTRIAN"][0])
    assert result["mean"] == pytest.approx((0.15, 0.5))
    three = threeway_epe(
        av2_bucket_stats(
            pc0,
            pred,
            gt,
            I4,
            classes,
            class_to_meta=THREEWAY_META,
            edges=THREEWAY_EDGES,
            metas=("BACKGROUND", "FOREGROUND"),
        )
    )
    assert three == pytest.approx(
        {"foreground_dynamic": 0.5, "foreground_static": 0.1, "background_static": 0.2, "threeway": 0.8 / 3}
    )


def test_meta_mapping_matches_package():
    pytest.importorskip("bucketed_scene_flow_eval", reason="bucketed-scene-flow-eval not installed")
    from bucketed_scene_flow_eval.datasets.argoverse2.argoverse_scene_flow import CATEGORY_MAP
    from bucketed_scene_flow_eval.datasets.argoverse2.av2_metacategories import BUCKETED_METACATAGORIES

    theirs = {
        cid + 1: meta
        for meta, names in BUCKETED_METACATAGORIES.items()
        for cid, name in CATEGORY_MAP.items()
        if name in names
    }
    assert theirs == AV2_META


AV2_LOG_PARTS = ("av2", "sensor", "val", "7fab2350-7eaf-3b7e-a39d-6937a4c1bede")
AV2_LOG = shared(*AV2_LOG_PARTS)


@needs_shared(*AV2_LOG_PARTS, "flow_labels.feather", what="the real Argoverse 2 log's flow labels", kind="exists")
def test_parity_on_real_av2_pair(tmp_path):
    pytest.importorskip("bucketed_scene_flow_eval", reason="bucketed-scene-flow-eval not installed")
    import pandas as pd
    from bucketed_scene_flow_eval.datasets.argoverse2.argoverse_scene_flow import CATEGORY_MAP
    from bucketed_scene_flow_eval.datasets.argoverse2.av2_metacategories import (
        BUCKETED_METACATAGORIES,
        THREEWAY_EPE_METACATAGORIES,
    )
    from bucketed_scene_flow_eval.eval import BucketedEPEEvaluator, ThreeWayEPEEvaluator

    labels = pd.read_feather(AV2_LOG / "flow_labels.feather")
    sweep = min((AV2_LOG / "sensors" / "lidar").glob("*.feather"))
    pc0 = pd.read_feather(sweep)[["x", "y", "z"]].to_numpy(np.float32)
    gt = labels[["flow_tx_m", "flow_ty_m", "flow_tz_m"]].to_numpy(np.float32)
    ego = np.load(AV2_LOG / "ego_motion.npz")["ego_motion"][0].astype(np.float64)
    classes = labels["classes"].to_numpy(np.int32)
    ground = labels["is_ground_0"].to_numpy(bool)
    frame = (pc0, ego_flow(pc0, ego), gt, ego, classes, ground)  # ego flow as the prediction
    evaluator = BucketedEPEEvaluator(
        CATEGORY_MAP, output_path=tmp_path / "b", meta_class_lookup=BUCKETED_METACATAGORIES
    )
    ref = _package_results(evaluator, [frame])
    mine = bucketed_epe(av2_bucket_stats(*frame[:5], ground=ground))
    assert mine["per_class"]["CAR"][1] > 0.5  # moving cars: ego flow misses their motion
    for meta in META_CLASSES:
        np.testing.assert_allclose(mine["per_class"][meta], ref[meta], atol=1e-6, rtol=0)
    np.testing.assert_allclose(mine["mean"], _package_mean(evaluator), atol=1e-6, rtol=0)
    ref3 = _package_results(
        ThreeWayEPEEvaluator(CATEGORY_MAP, THREEWAY_EPE_METACATAGORIES, output_path=tmp_path / "t"), [frame]
    )
    three = threeway_epe(
        av2_bucket_stats(
            *frame[:5],
            ground=ground,
            class_to_meta=THREEWAY_META,
            edges=THREEWAY_EDGES,
            metas=("BACKGROUND", "FOREGROUND"),
        )
    )
    np.testing.assert_allclose(
        [three["background_static"], three["foreground_static"], three["foreground_dynamic"]],
        [ref3["BACKGROUND"][0], ref3["FOREGROUND"][0], ref3["FOREGROUND"][1]],
        atol=1e-6,
    )
