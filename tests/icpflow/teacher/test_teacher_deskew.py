"""The de-skew refinement (icpflow.teacher.deskew) on a scene scanned by a rolling shutter with exact times."""

from __future__ import annotations

import numpy as np
import pytest

from icpflow.core.geometry import make_transform, transform_points
from icpflow.teacher import ICPFlow, ICPFlowConfig
from icpflow.teacher.config import ICPConfig
from icpflow.teacher.registration import register_plane
from icpflow.teacher.registration.icp import normals

from helpers.teacher_scenes import box_surface  # tests/ is on sys.path (pytest prepend import mode)

EGO = make_transform(yaw=0.02, translation=(0.8, 0.1, 0.0))
CFG = ICPFlowConfig.preset(
    "waymo", ground={"method": "zthreshold", "range_z": 0.0, "slack": 0.1}, ego_motion={"method": "given"}
)
DT = 0.1
VELOCITY = np.array([10.0, 0.0, 0.0])  # the car, m/s, in the ego frame of t


def rolling_shutter_scene(seed: int = 0) -> dict:
    """A car driving at VELOCITY past three parked boxes on a ground grid, each scan captured over 0.1 s.

    Static points are where they are whatever their time (the sweeps are ego-compensated). A car point captured
    ``time`` seconds after its scan's timestamp lies ``VELOCITY * time`` further on. The car sits at the sweep's
    seam: scan 0 catches it late (0.05 to 0.09 s), scan 1 early (0.01 to 0.05 s), so between the scans it seems
    to move 0.6 m, not the 1.0 m it moves between the timestamps, and each scan smears it over 0.4 m. Exact full
    flow of pc0: the motion between the timestamps (``VELOCITY * DT``) applied to the measured points.
    """
    rng = np.random.default_rng(seed)
    boxes = [((4.0, 1.8, 1.5), (-6.0, -4.0)), ((2.0, 2.0, 3.0), (3.0, -8.0)), ((6.0, 1.0, 2.0), (-10.0, 6.0))]
    statics0, statics1 = [], []
    for index, (size, (x, y)) in enumerate(boxes):
        place = make_transform(yaw=0.3 * index, translation=(x, y, 0.25))
        statics0.append(transform_points(place, box_surface(size, rng, spacing=0.12)))
        statics1.append(transform_points(place, box_surface(size, rng, spacing=0.12)))
    grid = np.stack(np.meshgrid(np.arange(-20, 20, 0.5), np.arange(-20, 20, 0.5)), -1).reshape(-1, 2)
    ground = np.c_[grid, np.zeros(len(grid))]
    car_place = make_transform(yaw=0.0, translation=(8.0, 3.0, 0.25))
    car0 = transform_points(car_place, box_surface((4.5, 1.9, 1.6), rng, spacing=0.12))
    car1 = transform_points(car_place, box_surface((4.5, 1.9, 1.6), rng, spacing=0.12))
    car_time0 = rng.uniform(0.05, 0.09, len(car0))
    car_time1 = rng.uniform(0.01, 0.05, len(car1))
    car0 = car0 + car_time0[:, None] * VELOCITY
    car1 = car1 + (DT + car_time1[:, None]) * VELOCITY  # still in the ego frame of t
    static0 = np.concatenate(statics0 + [ground + rng.normal(0, 0.01, ground.shape)])
    static1 = np.concatenate(statics1 + [ground + rng.normal(0, 0.01, ground.shape)])
    pc0 = np.concatenate([car0, static0]).astype(np.float32)
    pc1 = transform_points(EGO, np.concatenate([car1, static1])).astype(np.float32)
    time0 = np.r_[car_time0, rng.uniform(0, DT, len(static0))].astype(np.float32)
    time1 = np.r_[car_time1, rng.uniform(0, DT, len(static1))].astype(np.float32)
    car = np.r_[np.ones(len(car0), bool), np.zeros(len(static0), bool)]
    moved = pc0.astype(np.float64) + car[:, None] * VELOCITY * DT
    flow = (transform_points(EGO, moved) - pc0).astype(np.float32)
    return {"pc0": pc0, "pc1": pc1, "time0": time0, "time1": time1, "flow": flow, "car": car}


@pytest.fixture(scope="module")
def shutter():
    return rolling_shutter_scene()


@pytest.fixture(scope="module")
def results(shutter):
    s = shutter
    out = {}
    for deskew in (False, True):
        teacher = ICPFlow(CFG.replace(deskew={"enabled": deskew}))
        out[deskew] = teacher(s["pc0"], s["pc1"], EGO, time0=s["time0"], time1=s["time1"], dt=DT)
    return out


def test_deskew_recovers_the_motion_between_the_timestamps(shutter, results):
    car = shutter["car"]
    error = {k: np.linalg.norm(r.flow - shutter["flow"], axis=1) for k, r in results.items()}
    assert results[True].n_deskewed == 1 and results[False].n_deskewed == 0
    # point-to-point ICP between the smeared clusters lands 0.1 m short (measured 0.108), de-skewed: 0.012
    assert error[False][car].mean() > 0.08
    assert error[True][car].mean() < 0.03
    assert results[True].confidence[car].min() > 0
    # the static world is untouched: its flow is the ego flow either way
    static = ~car
    np.testing.assert_array_equal(results[True].flow[static], results[False].flow[static])
    assert error[True][static].max() < 0.02


def test_without_times_or_deskew_nothing_changes(shutter, results):
    s = shutter
    plain = ICPFlow(CFG.replace(deskew={"enabled": True}))(s["pc0"], s["pc1"], EGO)  # no times: no de-skew
    assert plain.n_deskewed == 0
    np.testing.assert_array_equal(plain.flow, results[False].flow)


@pytest.mark.parametrize(
    "kwargs, words",
    [
        (dict(time0="pc0", time1="pc1"), "needs time0, time1 and dt"),
        (dict(time0="pc0", dt=DT), "needs time0, time1 and dt"),
        (dict(time0="pc0", time1="pc1", dt=0.0), "dt must be a positive"),
        (dict(time0="short", time1="pc1", dt=DT), r"time0 must have shape"),
        (dict(time0="nan", time1="pc1", dt=DT), "time0 must hold finite float seconds"),
    ],
)
def test_bad_times_raise_one_line(shutter, kwargs, words):
    s = shutter
    values = {
        "pc0": s["time0"],
        "pc1": s["time1"],
        "short": s["time0"][:-1],
        "nan": np.full(len(s["time0"]), np.nan, np.float32),
    }
    kwargs = {k: values[v] if isinstance(v, str) else v for k, v in kwargs.items()}
    with pytest.raises(ValueError, match=words) as info:
        ICPFlow(CFG.replace(deskew={"enabled": True}))(s["pc0"], s["pc1"], EGO, **kwargs)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("overrides", [{"enabled": "yes"}, {"iters": 0}, {"min_speed": -1.0}])
def test_deskew_config_is_validated(overrides):
    with pytest.raises(ValueError, match=next(iter(overrides))):
        ICPFlowConfig.preset("av2", deskew=overrides)


def test_presets_deskew_only_av2():
    assert ICPFlowConfig.preset("av2").deskew.enabled
    assert not ICPFlowConfig.preset("waymo").deskew.enabled and not ICPFlowConfig.preset("nuscenes").deskew.enabled


def test_point_to_plane_registration_is_exact_on_a_box():
    rng = np.random.default_rng(3)
    box = box_surface((4.5, 1.9, 1.6), rng)
    truth = make_transform(yaw=0.04, translation=(0.6, -0.2, 0.03))
    moved = transform_points(truth, box_surface((4.5, 1.9, 1.6), rng, spacing=0.12))
    start = make_transform(translation=(0.55, -0.17, 0.0))
    result = register_plane([(box, moved)], start[None], ICPConfig())
    np.testing.assert_allclose(result.transforms[0], truth, atol=0.01)
    assert result.mean_error[0] < 0.05 and result.iou_ratio[0] > 0.3
    # normals of a flat face are perpendicular to it
    face = np.c_[rng.uniform(0, 2, 200), rng.uniform(0, 2, 200), np.zeros(200)]
    np.testing.assert_allclose(np.abs(normals(face)[:, 2]), 1.0, atol=1e-6)
