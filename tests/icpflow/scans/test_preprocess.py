"""The typed preprocessing block (``icpflow.scans.preprocess``): its frames, its stored form and the older forms it
reads,
and the height-frame transforms."""

import json

import numpy as np
import pytest
import yaml
from hydra import compose, initialize_config_dir

from icpflow.core.geometry import make_transform, transform_points
from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.scans.ground import GroundSegmenter
from icpflow.scans.preprocess import (
    Preprocessing,
    PreprocessingError,
    estimate_ground_height,
    implausible,
    lift_points,
    lift_pose,
    lift_transform,
)
from icpflow.teacher.config import ICPFlowConfig, teacher_config

from helpers.data import REPO


def dataset_teacher(name: str) -> ICPFlowConfig:
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return teacher_config(compose("label", [f"dataset={name}", "dataset.root=unused"]))


@pytest.mark.parametrize(
    "name, ground_z",
    [("synthetic", 0.0), ("kitti", 0.0), ("sequence", 0.0), ("waymo", 0.0), ("av2", -0.323), ("nuscenes", -1.723)],
)
def test_each_dataset_teacher_names_its_height_frame(name, ground_z):
    """The frame follows from where the teacher's Patchwork++ settings expect the ground: z = 0 for the synthetic
    world and for KITTI and your own scans as their readers lift them; -0.32 m at AV2's rear-axle origin; the
    nuScenes preset works in PCAccumulation's lidar frame (ground 1.7 m below)."""
    teacher = dataset_teacher(name)
    block = Preprocessing.from_teacher(teacher)
    assert block.frame.ground_z == pytest.approx(ground_z)
    assert block.patchwork_z_offset == pytest.approx(teacher.ground.patchwork_z_offset)
    assert block.ground == teacher.ground and block.ego_motion == teacher.ego_motion  # the teacher's own blocks
    rebuilt = ICPFlowConfig.preset("waymo").replace(**block.teacher_fields())
    assert (rebuilt.ground, rebuilt.ego_motion) == (teacher.ground, teacher.ego_motion)


def test_stored_form_round_trips_through_json_and_yaml():
    block = Preprocessing.from_teacher(
        ICPFlowConfig.preset("av2", ground={"sensor_height": 1.5}, ego_motion={"kiss_voxel_size": 0.5})
    )
    stored = block.to_dict()
    assert stored["version"] == 1 and stored["frame"] == {"ground_z": -0.1}
    assert stored["ground"]["sensor_height"] == 1.5 and stored["ego_motion"]["kiss_voxel_size"] == 0.5
    assert Preprocessing.from_dict(json.loads(json.dumps(stored))) == block
    assert Preprocessing.from_dict(yaml.safe_load(yaml.safe_dump(stored))) == block


def test_older_forms_are_read():
    """Shards, checkpoints and exports of older versions carried a flat dict of teacher fields (all of them in
    shards, nine in checkpoints and exports) or nothing: they read as the block of the frame they were made in."""
    synthetic = ICPFlowConfig.preset(
        "waymo", ground={"method": "both", "sensor_height": 1.9, "patchwork_z_offset": -1.9}
    )  # the ground of every release before the local method
    from_shard = Preprocessing.from_dict(synthetic.to_dict())  # a shard's nested teacher config
    nine = dict(ground="both", sensor_height=1.9, patchwork_max_range=64.0, patchwork_z_offset=-1.9, range_z=0.04)
    nine.update(ground_slack=0.3, kiss_voxel_size=1.0, kiss_max_range=100.0, ego_refine_voxel=0.2)
    from_checkpoint = Preprocessing.from_dict(nine)  # the flat names of older checkpoints and exports
    from_old_shard = Preprocessing.from_dict({**nine, "ego_motion": "given", "crop_xy": 32.0, "min_cluster_size": 30})
    assert from_shard == from_checkpoint == from_old_shard == Preprocessing.from_teacher(synthetic)
    assert Preprocessing.from_dict({**nine, "ground": "zthreshold", "ego_motion": "kiss_icp"}).ground.method == (
        "zthreshold"
    )
    assert from_shard.frame.ground_z == 0.0 and from_shard.ground.sensor_height == 1.9
    assert Preprocessing.from_dict(None).frame.ground_z == 0.0  # an export without teacher settings
    # a stored form older than the local ground method keeps the ground of its time, named or not
    assert Preprocessing.from_dict(None).ground.method == "both"
    unnamed = {key: value for key, value in nine.items() if key != "ground"}
    assert Preprocessing.from_dict(unnamed).ground.method == "both"
    assert Preprocessing.from_dict({"ground": {"sensor_height": 1.9}}).ground.method == "both"
    assert Preprocessing().ground.method == "local"  # what is written now
    # the ground masks of the older form and of the block are the same masks
    pair = SyntheticDataset(split="val", beams=32, num_sequences=1, frames_per_sequence=2)[0]
    assert np.array_equal(GroundSegmenter(synthetic)(pair.pc0), GroundSegmenter(from_shard)(pair.pc0))


def test_bad_blocks_are_one_line_errors():
    with pytest.raises(PreprocessingError, match=r"newer than this code's \(1\)"):
        Preprocessing.from_dict({"version": 7})
    with pytest.raises(PreprocessingError, match=r"GroundConfig: method must be one of .*, got 'sometimes'"):
        Preprocessing.from_dict({"version": 1, "ground": {"method": "sometimes"}})
    with pytest.raises(PreprocessingError, match="unexpected keyword argument 'colour'"):
        Preprocessing.from_dict({"version": 1, "ground": {"colour": 1}})
    with pytest.raises(PreprocessingError, match="EgoMotionConfig: kiss_voxel_size must be a number > 0, got 0"):
        Preprocessing.from_dict({"version": 1, "ego_motion": {"kiss_voxel_size": 0}})


def test_lift_keeps_every_flow_and_maps_poses():
    """Raising two frames by the same height conjugates the ego motion and changes no flow vector."""
    rng = np.random.default_rng(0)
    points = rng.uniform(-20, 20, (100, 3)).astype(np.float32)
    ego = make_transform(yaw=0.05, pitch=0.01, translation=(1.0, 0.2, 0.05))
    lifted_ego = lift_transform(ego, 1.73)
    flow = transform_points(ego, points) - points
    lifted = lift_points(points, 1.73)
    assert lifted is not points and np.allclose(lifted[:, 2], points[:, 2] + 1.73)
    np.testing.assert_allclose(transform_points(lifted_ego, lifted) - lifted, flow, atol=1e-5)
    pose0, pose1 = make_transform(yaw=0.3, translation=(5, 1, 0)), make_transform(yaw=0.35, translation=(6, 1, 0))
    relative = np.linalg.inv(lift_pose(pose1, 1.73)) @ lift_pose(pose0, 1.73)
    np.testing.assert_allclose(relative, lift_transform(np.linalg.inv(pose1) @ pose0, 1.73), atol=1e-12)
    assert lift_points(points, 0.0) is points


def test_ground_height_and_plausibility():
    pair = SyntheticDataset(split="val", beams=32, num_sequences=1, frames_per_sequence=2)[0]
    assert abs(estimate_ground_height(pair.pc0)) < 0.1  # the synthetic ground is at z = 0 (gently sloped)
    assert abs(estimate_ground_height(lift_points(pair.pc0, -2.4)) + 2.4) < 0.1
    assert implausible(0.5, 0.9) is None
    assert implausible(0.92, 0.9) == "92% of the points called ground (> 85%)"
    assert "10% of the points inside the network's grid (< 20%)" in implausible(0.5, 0.1)
