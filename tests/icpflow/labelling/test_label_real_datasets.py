"""label.py end to end on the real samples in ../shared/data (Argoverse 2, bare KITTI scans), and through the same
composed config and reader instantiation on small files in the PCAccumulation (Waymo, nuScenes) and ZeroFlow layouts.

Each run labels one sample (``limit=1``) and the shard is read back with ``ShardDataset``.
"""

import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from hydra import compose, initialize_config_dir

from icpflow.labelling.cli import label
from icpflow.shards import ShardDataset

from helpers.data import REPO, needs_shared, shared
from helpers.pcaccumulation import FORMATS, WAYMO_CLASSES, world, write_dataset  # tests/ is on sys.path
from helpers.zeroflow import LOG, dump_arrays, write_dump

AV2_ROOT = shared("av2")
KITTI_SCANS = shared("kitti_hdl64_scans")
#: one sample, in this process's worker, HDBSCAN without its process pool (the same labels, no pool start-up)
ONE = ["limit=1", "workers=1", "icpflow.clustering.n_jobs=1"]


def label_script(tmp_path, *overrides) -> dict:
    """Run ``label.py`` in a subprocess; the one labelled sample of its shards."""
    out = tmp_path / "labels"
    done = subprocess.run(
        [
            sys.executable,
            str(REPO / "label.py"),
            *overrides,
            *ONE,
            f"out_dir={out}",
            f"hydra.run.dir={tmp_path / 'hydra'}",
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert "1 samples labelled" in done.stdout and "0 failed" in done.stdout
    shards = ShardDataset(out)
    assert len(shards) == 1
    return shards[0]


@needs_shared("av2", what="the real Argoverse 2 sample")
def test_label_py_on_the_real_av2_log(tmp_path):
    pytest.importorskip("av2", reason="the av2 package is not installed (pip install icpflow[av2])")
    from icpflow.datasets.av2 import AV2Dataset

    sample = label_script(tmp_path, "dataset=av2", f"dataset.root={AV2_ROOT}", "split=val")
    (log,) = (AV2_ROOT / "sensor" / "val").iterdir()
    sweeps = sorted((log / "sensors" / "lidar").glob("*.feather"))
    rows = [len(pd.read_feather(path, columns=["x"])) for path in sweeps]
    assert sample["pc0"].shape == (rows[0], 3) and sample["pc1"].shape == (rows[1], 3)
    pair = AV2Dataset(AV2_ROOT, "val").pair(0)
    assert sample["sample_id"] == f"{log.name}/{sweeps[0].stem}"
    np.testing.assert_array_equal(sample["pc0"], pair.pc0)
    np.testing.assert_array_equal(sample["gt_flow"], pair.flow)
    np.testing.assert_array_equal(sample["gt_classes"], pair.classes)
    np.testing.assert_array_equal(sample["gt_dynamic"], pair.dynamic)
    np.testing.assert_allclose(sample["ego1_from_ego0"], pair.ego1_from_ego0, atol=1e-9)  # from the poses
    flow = sample["flow"]
    assert flow.shape == pair.pc0.shape and np.isfinite(flow).all()
    error = np.linalg.norm(flow - pair.flow, axis=1)
    moving, still = ~pair.ground0 & pair.dynamic, ~pair.ground0 & ~pair.dynamic
    assert moving.sum() > 1000 and np.linalg.norm(pair.residual_flow()[moving], axis=1).mean() > 0.5
    assert error[moving].mean() < 0.3 and error[still].mean() < 0.05  # the teacher follows the moving objects


@needs_shared("kitti_hdl64_scans", what="the real KITTI HDL-64 scans")
def test_label_py_on_the_bare_kitti_scans(tmp_path):
    sample = label_script(tmp_path, "dataset=kitti", f"dataset.root={KITTI_SCANS}")  # a bare folder: no poses
    scans = [np.fromfile(KITTI_SCANS / f"{frame:06d}.bin", np.float32).reshape(-1, 4) for frame in (0, 1)]
    lift = np.float32([0, 0, 1.73])  # the reader's height frame: the velodyne frame lifted onto the ground
    np.testing.assert_array_equal(sample["pc0"], scans[0][:, :3] + lift)
    np.testing.assert_array_equal(sample["pc1"], scans[1][:, :3] + lift)
    assert sample["sample_id"] == "kitti_hdl64_scans/000000" and "gt_flow" not in sample
    assert sample["flow"].shape == sample["pc0"].shape and np.isfinite(sample["flow"]).all()
    assert 0.5 < np.linalg.norm(sample["ego1_from_ego0"][:3, 3]) < 0.9  # KISS-ICP: the car drives ~0.7 m a frame


def _label_in_process(out, *overrides) -> dict:
    """``label(cfg)`` on the config label.py composes (same reader instantiation); the one labelled sample."""
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("label", [*overrides, *ONE, f"out_dir={out}"])
    assert label(cfg, progress=False) == 0
    shards = ShardDataset(out)
    assert len(shards) == 1
    return shards[0]


@pytest.mark.parametrize("dataset", ["waymo", "nuscenes"])
def test_pcaccumulation_configs_label_files_in_the_real_layout(tmp_path, dataset):
    write_dataset(tmp_path / "data", dataset)
    sample = _label_in_process(
        tmp_path / "labels", f"dataset={dataset}", f"dataset.root={tmp_path / 'data'}", "split=val"
    )
    truth = world(dataset).pair(FORMATS[dataset][0] - 2, 1)  # frame c = 1 into the anchor
    assert sample["sample_id"] == "val/seg/000/1"
    np.testing.assert_array_equal(sample["pc0"], truth.pc0)
    np.testing.assert_array_equal(sample["pc1"], truth.pc1)
    np.testing.assert_allclose(sample["gt_flow"], truth.flow, atol=1e-5)
    foreground = (truth.classes > 0).astype(np.int32)
    classes = WAYMO_CLASSES[truth.classes] if dataset == "waymo" else foreground
    np.testing.assert_array_equal(sample["gt_classes"], classes)
    assert np.isfinite(sample["flow"]).all()


def test_zeroflow_config_labels_a_dump(tmp_path):
    write_dump(tmp_path / "data")
    sample = _label_in_process(
        tmp_path / "labels", "dataset=zeroflow_av2", f"dataset.root={tmp_path / 'data'}", "split=val"
    )
    arrays = dump_arrays()
    assert sample["sample_id"] == f"{LOG}/000007" and sample["pc0"].shape == sample["pc1"].shape == (250, 3)
    np.testing.assert_array_equal(sample["pc0"], arrays["pc1"][:250])
    np.testing.assert_array_equal(sample["gt_flow"], arrays["gt_flow_0_1"][:250])
    assert np.isfinite(sample["flow"]).all()
