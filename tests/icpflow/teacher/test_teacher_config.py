"""The teacher's typed config: per-step blocks, constraints on the fields, the Hydra schema, the older flat names
(deprecated for one release) and the older stored forms (shards, checkpoints, exports) that still load."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import yaml
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf

from icpflow.core.errors_and_signals import error_line
from icpflow.teacher.config import (
    BLOCKS,
    ChecksConfig,
    ClusteringConfig,
    DeskewConfig,
    EgoMotionConfig,
    GroundConfig,
    HistogramConfig,
    ICPConfig,
    ICPFlowConfig,
    PairingConfig,
    teacher_config,
)

from helpers.data import REPO

CONF = REPO / "conf"

# The previous release's ICPFlowConfig: its 47 flat fields and their defaults, and its presets (test data, copied
# from that release's icpflow/teacher/config.py).
OLD_DEFAULTS = dict(
    dataset="custom",
    ego_motion="given",
    kiss_voxel_size=1.0,
    kiss_max_range=100.0,
    ego_refine_voxel=0.2,
    ground="both",
    sensor_height=1.723,
    patchwork_max_range=64.0,
    patchwork_z_offset=0.0,
    range_z=0.04,
    ground_slack=0.3,
    crop_xy=32.0,
    min_cluster_size=30,
    max_clusters=200,
    cluster_voxel_size=0.0,
    hdbscan_epsilon=0.25,
    hdbscan_min_samples=None,
    hdbscan_leaf_size=100,
    hdbscan_n_jobs=2,
    speed=1.67,
    max_frame_gap=4,
    extent_ratio=0.1,
    init="histogram",
    hist_bin=0.1,
    hist_z_bins=3,
    hist_z_range=0.1,
    nms_kernel=11,
    top_k=5,
    hist_max_points=1000,
    max_points=10000,
    icp_max_corr=0.1,
    icp_max_iter=100,
    icp_rel_rmse=1e-6,
    icp_backend="cpu",
    icp_dof="full",
    static_tolerance=0.0,
    deskew=False,
    deskew_min_speed=1.0,
    deskew_iters=2,
    min_iou=0.2,
    max_roll_pitch_deg=9.0,
    max_error=0.3,
    association="argmin",
    absorb_radius=0.0,
    conf_iou_full=0.5,
    seed=0,
)
_COMMON = dict(static_tolerance=0.25, max_clusters=200, hdbscan_epsilon=0.25, icp_max_corr=0.1, min_iou=0.2)
OLD_PRESETS = {
    "waymo": dict(
        _COMMON,
        dataset="waymo",
        patchwork_z_offset=-1.723,
        crop_xy=32.0,
        range_z=0.04,
        ground_slack=0.3,
        min_cluster_size=30,
        speed=1.67,
        max_points=10000,
        extent_ratio=0.1,
        max_error=0.3,
    ),
    "nuscenes": dict(
        _COMMON,
        dataset="nuscenes",
        crop_xy=32.0,
        range_z=-1.84,
        ground_slack=0.3,
        min_cluster_size=20,
        speed=0.833333,
        max_points=5000,
        extent_ratio=0.1,
        max_error=0.2,
    ),
    "av2": dict(
        _COMMON,
        dataset="av2",
        hist_max_points=300,
        crop_xy=51.2,
        range_z=-10000.0,
        ground_slack=0.0,
        patchwork_z_offset=-1.4,
        cluster_voxel_size=0.25,  # 0.2 before issue 22
        absorb_radius=0.5,
        deskew=True,
        min_cluster_size=20,
        speed=1.0,
        max_points=10000,
        extent_ratio=0.1,
        max_error=0.2,
    ),
}
# The flat ground and ego-motion fields that older shards, checkpoints and exports carry.
PREPROCESSING = (
    "ground",
    "sensor_height",
    "patchwork_max_range",
    "patchwork_z_offset",
    "range_z",
    "ground_slack",
    "kiss_voxel_size",
    "kiss_max_range",
    "ego_refine_voxel",
)


def _quiet(build):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # any warning fails the test
        return build()


def _compose(*overrides):
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return compose("label", ["dataset.root=/nowhere", *overrides])


# ------------------------------------------------------------------------------------------- defaults, presets


def test_defaults_and_presets_are_the_previous_releases():
    """Every setting the teacher used before the blocks keeps its value, defaults and presets alike (the
    histogram vote's points included: 1000 by default, 300 for av2, as the pipeline read them), but for the steps
    added since: issue 30's for long vehicles, issue 42's ground that keeps moving objects (``ground.method``
    ``local``; the older ``both`` is named in every stored form), the plane test of static matches
    (``icp.plane_gain``) and the twin check (``checks.max_twin_share``)."""
    assert _quiet(lambda: ICPFlowConfig.from_dict(OLD_DEFAULTS, warn=False)) == ICPFlowConfig(
        ground={**ICPFlowConfig().to_dict()["ground"], "method": "both"}
    )
    assert ICPFlowConfig().ground.method == "local"
    for name, old in OLD_PRESETS.items():
        assert _quiet(lambda old=old: ICPFlowConfig.from_dict({**OLD_DEFAULTS, **old}, warn=False)) == (
            ICPFlowConfig.preset(
                name,
                histogram={"axis_min_extent": 0.0},
                merging={"distance": 0.0, "static_iou": 0.0},
                ground={"method": "both"},
                icp={"plane_gain": 0.0},
                checks={"max_twin_share": 1.0},
            )
        )
        assert ICPFlowConfig.preset(name).ground.method == "local"
    assert ICPFlowConfig().histogram.max_points == 1000 and ICPFlowConfig.preset("av2").histogram.max_points == 300
    assert HistogramConfig() == ICPFlowConfig().histogram and ICPConfig() == ICPFlowConfig().icp


def test_round_trip_through_a_dict_and_yaml():
    cfg = ICPFlowConfig.preset("av2", clustering={"n_jobs": 1}, **{"icp.backend": "torch"})
    assert ICPFlowConfig(**cfg.to_dict()) == cfg
    assert ICPFlowConfig.from_dict(yaml.safe_load(yaml.safe_dump(cfg.to_dict()))) == cfg
    assert cfg.clustering == dataclasses.replace(ICPFlowConfig.preset("av2").clustering, n_jobs=1)
    assert cfg.icp.backend == "torch" and cfg.icp.static_tolerance == 0.25  # the rest of the block kept


# ----------------------------------------------------------------------------------------------- constraints


@pytest.mark.parametrize(
    "build, words",
    [
        (
            lambda: ClusteringConfig(min_cluster_size=0),
            "ClusteringConfig: min_cluster_size must be an integer >= 1.*got 0",
        ),
        (lambda: ClusteringConfig(min_cluster_size=2.5), "min_cluster_size must be an integer.*got 2.5"),
        (lambda: ClusteringConfig(min_samples=0), "min_samples must be None or an integer >= 1.*got 0"),
        (lambda: ClusteringConfig(voxel_size=-0.1), "voxel_size must be a number >= 0.*got -0.1"),
        (lambda: PairingConfig(speed=0.0), "speed must be a number > 0.*got 0.0"),
        (lambda: PairingConfig(extent_ratio=1.5), "extent_ratio must be a number in \\[0, 1\\].*got 1.5"),
        (lambda: HistogramConfig(nms_kernel=10), "nms_kernel must be an odd integer.*got 10"),
        (lambda: HistogramConfig(init="median"), "init must be one of histogram, centroid, got 'median'"),
        (lambda: ICPConfig(backend="cuda"), "backend must be one of.*got 'cuda'"),
        (lambda: ICPConfig(max_iter=-1), "max_iter must be an integer >= 0.*got -1"),
        (lambda: ICPConfig(max_corr=float("nan")), "max_corr must be a number > 0.*got nan"),
        (lambda: DeskewConfig(enabled="yes"), "enabled must be true or false.*got 'yes'"),
        (lambda: ChecksConfig(min_iou=True), "min_iou must be a number in.*got True"),
        (lambda: GroundConfig(method="x"), "GroundConfig: method must be one of.*got 'x'"),
        (lambda: GroundConfig(range_z="low"), "range_z must be a number.*got 'low'"),
        (lambda: GroundConfig(slack=-0.1), "slack must be a number >= 0.*got -0.1"),
        (lambda: EgoMotionConfig(method="gps"), "EgoMotionConfig: method must be one of.*got 'gps'"),
        (lambda: EgoMotionConfig(kiss_voxel_size=0), "kiss_voxel_size must be a number > 0.*got 0"),
        (lambda: ICPFlowConfig(ground="both"), "ground must be a GroundConfig"),
        (lambda: ICPFlowConfig(seed=1.0), "seed must be an integer.*got 1.0"),
        (lambda: ICPFlowConfig(clustering=3), "clustering must be a ClusteringConfig"),
        (lambda: ICPFlowConfig().replace(clustering={"bogus": 1}), "unknown field\\(s\\) \\['clustering.bogus'\\]"),
        (lambda: ICPFlowConfig().replace(**{"icp.bogus": 1}), "unknown field\\(s\\) \\['icp.bogus'\\]"),
        (lambda: ICPFlowConfig().replace(pairing=4), "pairing must be a dict of PairingConfig fields"),
        (lambda: ICPFlowConfig.preset("av2", bogus=1, other=2), "unknown field\\(s\\) \\['bogus', 'other'\\]"),
    ],
)
def test_constraints_on_the_fields_are_one_line_errors(build, words):
    with pytest.raises(ValueError, match=words) as info:
        build()
    assert "\n" not in str(info.value)


def test_every_field_declares_a_constraint():
    """A field without a rule or choices would take any value: every setting names what it accepts."""
    for kind in (ICPFlowConfig, *BLOCKS.values()):
        for f in dataclasses.fields(kind):
            if f.name not in BLOCKS:
                assert f.metadata.get("rule") or f.metadata.get("choices"), f"{kind.__name__}.{f.name}"


# ------------------------------------------------------------------------------------------------- old names


# a valid value other than the waymo preset's for each setting that moved into a block: old name -> (new, value)
MOVED = {
    "ego_motion": ("ego_motion.method", "kiss_icp"),
    "kiss_voxel_size": ("ego_motion.kiss_voxel_size", 0.5),
    "kiss_max_range": ("ego_motion.kiss_max_range", 60.0),
    "ego_refine_voxel": ("ego_motion.refine_voxel", 0.3),
    "ground": ("ground.method", "patchwork"),
    "sensor_height": ("ground.sensor_height", 1.9),
    "patchwork_max_range": ("ground.patchwork_max_range", 50.0),
    "patchwork_z_offset": ("ground.patchwork_z_offset", -1.0),
    "range_z": ("ground.range_z", 0.1),
    "ground_slack": ("ground.slack", 0.2),
    "min_cluster_size": ("clustering.min_cluster_size", 12),
    "max_clusters": ("clustering.max_clusters", 50),
    "cluster_voxel_size": ("clustering.voxel_size", 0.1),
    "hdbscan_epsilon": ("clustering.epsilon", 0.5),
    "hdbscan_min_samples": ("clustering.min_samples", 3),
    "hdbscan_leaf_size": ("clustering.leaf_size", 40),
    "hdbscan_n_jobs": ("clustering.n_jobs", 1),
    "speed": ("pairing.speed", 2.0),
    "max_frame_gap": ("pairing.max_frame_gap", 2),
    "extent_ratio": ("pairing.extent_ratio", 0.3),
    "init": ("histogram.init", "centroid"),
    "hist_bin": ("histogram.bin_size", 0.2),
    "hist_z_bins": ("histogram.z_bins", 5),
    "hist_z_range": ("histogram.z_range", 0.3),
    "nms_kernel": ("histogram.nms_kernel", 7),
    "top_k": ("histogram.top_k", 3),
    "hist_max_points": ("histogram.max_points", 300),
    "max_points": ("icp.max_points", 2000),
    "icp_max_corr": ("icp.max_corr", 0.2),
    "icp_max_iter": ("icp.max_iter", 30),
    "icp_rel_rmse": ("icp.rel_rmse", 1e-4),
    "icp_backend": ("icp.backend", "torch"),
    "icp_dof": ("icp.dof", "yaw"),
    "static_tolerance": ("icp.static_tolerance", 0.5),
    "deskew": ("deskew.enabled", True),
    "deskew_min_speed": ("deskew.min_speed", 2.0),
    "deskew_iters": ("deskew.iters", 3),
    "min_iou": ("checks.min_iou", 0.3),
    "max_roll_pitch_deg": ("checks.max_roll_pitch_deg", 5.0),
    "max_error": ("checks.max_error", 0.25),
    "association": ("association.method", "hungarian"),
    "absorb_radius": ("flow.absorb_radius", 0.5),
    "conf_iou_full": ("flow.conf_iou_full", 0.6),
}


def test_every_old_flat_name_maps_to_its_block_with_a_one_line_warning():
    flat = {f.name for f in dataclasses.fields(ICPFlowConfig) if f.name not in BLOCKS}
    assert set(MOVED) | {"dataset"} == set(OLD_DEFAULTS) - flat
    for old, (new, value) in MOVED.items():
        with pytest.warns(FutureWarning) as caught:
            cfg = ICPFlowConfig.preset("waymo", **{old: value})
        (warning,) = caught
        assert str(warning.message) == (
            f"icpflow: '{old}' is deprecated, use '{new}'; the old name goes in the next release"
        )
        block, field = new.split(".")
        assert (
            getattr(getattr(cfg, block), field)
            == value
            != getattr(getattr(ICPFlowConfig.preset("waymo"), block), field)
        )
        assert _quiet(lambda new=new, value=value: ICPFlowConfig.preset("waymo", **{new: value})) == cfg
    with pytest.warns(FutureWarning, match="'dataset' is deprecated and ignored"):
        assert ICPFlowConfig.preset("waymo", dataset="av2") == ICPFlowConfig.preset("waymo")


def test_old_names_on_the_command_line_and_in_dataset_teacher_blocks():
    new = _quiet(
        lambda: teacher_config(
            _compose(
                "icpflow.deskew.enabled=true",
                "icpflow.association.method=hungarian",
                "icpflow.clustering.min_cluster_size=7",
                "icpflow.histogram.max_points=500",
                "icpflow.icp.backend=torch",
                "icpflow.ground.method=patchwork",
                "icpflow.ground.sensor_height=1.9",
                "icpflow.ego_motion.refine_voxel=0.3",
            )
        )
    )
    with pytest.warns(FutureWarning) as caught:
        old = teacher_config(
            _compose(
                "icpflow.deskew.enabled=true",
                "icpflow.association.method=hungarian",
                "icpflow.min_cluster_size=7",
                "icpflow.hist_max_points=500",
                "icpflow.icp_backend=torch",
                "icpflow.ground.method=patchwork",
                "icpflow.sensor_height=1.9",
                "icpflow.ego_refine_voxel=0.3",
                "icpflow.dataset=waymo",
            )
        )
    assert old == new and len(caught) == 6 and new.ground.method == "patchwork"
    # an older flat name that is a block's name is not read on the command line: every block is typed
    for override in ("icpflow.deskew=true", "icpflow.ground=patchwork", "icpflow.association=hungarian"):
        with pytest.raises(ConfigCompositionException) as refused:
            _compose(override)
        line = error_line(refused.value)
        key = override.split("=")[0]
        assert line.startswith(f"{override}: {key} is a block of settings, give one of its fields ({key}.<field>=...)")
    # a dataset's teacher block of the previous release (flat names) gives the same teacher as the nested one
    nested = _quiet(lambda: teacher_config(_compose("dataset=synthetic")))
    with pytest.warns(FutureWarning, match="'cluster_voxel_size' is deprecated, use 'clustering.voxel_size'"):
        flat = teacher_config(
            _compose(
                "dataset=synthetic",
                "dataset.teacher.clustering.voxel_size=null",
                "dataset.teacher.cluster_voxel_size=0.1",
            )
        )
    assert flat == nested and nested.clustering.voxel_size == 0.1
    with pytest.warns(FutureWarning) as caught:
        flat = teacher_config(
            _compose(
                "dataset=synthetic",
                "dataset.teacher.ground.sensor_height=null",
                "dataset.teacher.ground.patchwork_z_offset=null",
                "dataset.teacher.sensor_height=1.9",
                "dataset.teacher.patchwork_z_offset=-1.9",
            )
        )
    assert flat == nested and nested.ground.sensor_height == 1.9
    assert [str(w.message).split(";")[0] for w in caught] == [
        "icpflow: 'sensor_height' is deprecated, use 'ground.sensor_height'",
        "icpflow: 'patchwork_z_offset' is deprecated, use 'ground.patchwork_z_offset'",
    ]


# ------------------------------------------------------------------------------------------------------ Hydra


def test_the_hydra_schema_offers_every_field_and_no_yaml_lists_them():
    node = _compose("dataset=waymo").icpflow
    values = OmegaConf.to_container(node, resolve=True)
    assert values.pop("preset") == "waymo"
    for f in dataclasses.fields(ICPFlowConfig):
        if f.name in BLOCKS:
            assert set(values[f.name]) == {g.name for g in dataclasses.fields(BLOCKS[f.name])}
            assert set(values[f.name].values()) == {None}
        else:
            assert values[f.name] is None
    for path in (CONF / "icpflow").glob("*.yaml"):
        listed = set(yaml.safe_load(path.read_text())) - {"defaults", "preset"}
        assert not listed, f"{path.name} lists fields {listed}"


def test_hydra_overrides_are_typed_and_checked():
    from hydra.errors import ConfigCompositionException

    cfg = teacher_config(_compose("icpflow.icp.max_iter=7", "icpflow.crop_xy=40", "icpflow.flow.absorb_radius=0.3"))
    assert (cfg.icp.max_iter, cfg.crop_xy, cfg.flow.absorb_radius) == (7, 40.0, 0.3)
    for bad in ("icpflow.icp.max_iter=abc", "icpflow.clustering.bogus=1", "icpflow.bogus=1"):
        with pytest.raises(ConfigCompositionException):
            _compose(bad)
    with pytest.raises(ValueError, match="HistogramConfig: nms_kernel must be an odd integer.*got 4"):
        teacher_config(_compose("icpflow.histogram.nms_kernel=4"))


# ------------------------------------------------------------------------------------------- older stored forms


def test_an_older_shards_labeller_config_still_loads(tmp_path):
    """A shard of the previous release stores the teacher flat in its ``config`` attribute: the student reads its
    ground and ego settings from it, and the whole teacher rebuilds from it without a warning."""
    import h5py

    from fastflow3d.network.voxelize import Grid
    from fastflow3d.training.data import labeller_contract
    from icpflow.scans.preprocess import Preprocessing
    from icpflow.shards.schema import shard_name
    from icpflow.shards.writer import write_index, write_shard

    teacher = {**OLD_DEFAULTS, **OLD_PRESETS["waymo"], "sensor_height": 1.9, "cluster_voxel_size": 0.1}
    config = yaml.safe_dump({"split": "train", "teacher": teacher, "horizon": 1, "shard_size": 1})
    n = 4
    sample = {
        "pc0": np.zeros((n, 3), np.float32),
        "pc1": np.zeros((n, 3), np.float32),
        "ground0": np.zeros(n, bool),
        "ground1": np.zeros(n, bool),
        "ego1_from_ego0": np.eye(4),
        "flow": np.zeros((n, 3), np.float32),
        "confidence": np.zeros(n, np.float32),
        "cluster": np.full(n, -1, np.int32),
        "attrs": {"sample_id": "s0", "log_id": "log", "index": 0, "timestamp0_ns": -1, "timestamp1_ns": -1, "dt": 0.1},
    }
    write_shard(tmp_path / shard_name(0), [sample], config, "oldhash")
    entry = {"file": shard_name(0), "samples": [{"sample_id": "s0", "index": 0, "n0": n, "n1": n}]}
    write_index(tmp_path / "index.json", {"config_hash": "oldhash", "shards": [entry]})
    assert labeller_contract(tmp_path, True, Grid()).preprocessing == Preprocessing.from_teacher(teacher)
    with h5py.File(tmp_path / shard_name(0), "r") as handle:
        stored = yaml.safe_load(handle.attrs["config"])["teacher"]
    rebuilt = _quiet(lambda: ICPFlowConfig.from_dict(stored, warn=False))
    # as those labels were made: without the steps a later release added (issue 30's and the plane test, off by
    # their defaults, as the twin check; the ground they named, not issue 42's)
    assert rebuilt == ICPFlowConfig.preset(
        "waymo",
        ground={"sensor_height": 1.9, "method": "both"},
        clustering={"voxel_size": 0.1},
        histogram={"axis_min_extent": 0.0},
        merging={"distance": 0.0, "static_iou": 0.0},
        icp={"plane_gain": 0.0},
        checks={"max_twin_share": 1.0},
    )


def test_older_checkpoints_and_exports_still_load():
    """Checkpoints (``data.teacher``) and exports (``preprocessing.teacher``) of the previous releases carry the
    flat ground and ego-motion fields: both read silently as the same input contract
    (``fastflow3d.network.contract``)."""
    from fastflow3d.network.contract import upgrade
    from icpflow.scans.preprocess import Preprocessing

    old = {key: {**OLD_DEFAULTS, **OLD_PRESETS["av2"]}[key] for key in PREPROCESSING}
    expected = Preprocessing.from_teacher(ICPFlowConfig.from_dict(old, warn=False))
    grid = {"x_range": [-8.0, 8.0], "y_range": [-8.0, 8.0], "z_range": [-3.0, 3.0], "cell": 0.5}
    metadata = {"metadata_version": 1, "grid": grid, "preprocessing": {"remove_ground": True, "teacher": dict(old)}}
    checkpoint = {"model": grid, "data": {"teacher": dict(old), "train": "unused", "remove_ground": True}}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        from_export, from_checkpoint = upgrade(metadata), upgrade(checkpoint)
    assert from_export == from_checkpoint and from_export.preprocessing == expected
    assert from_export.preprocessing.patchwork_z_offset == -1.4 and from_export.grid.cell == 0.5
