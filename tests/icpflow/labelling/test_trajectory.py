"""A drive's trajectory is its own (``icpflow.labelling.trajectory``): the stored one is reused only for the same scan
files (absolute path, size, modification time) and settings; another drive with the same scan names, a replaced or
touched scan and ``overwrite=true`` estimate it afresh; a scan too small to register is no step, and the pairs across
it fail with that reason, for ``label.py`` as for the stream."""

import os

import numpy as np
import pytest

from icpflow.core.frame_pair import FramePairError
from icpflow.core.geometry import pose_error
from icpflow.datasets.scan_folder import ScanSequenceDataset
from icpflow.labelling.job import LabelJob
from icpflow.labelling.trajectory import NAME, drive_trajectory
from icpflow.scans.odometry import MIN_EGO_POINTS
from icpflow.teacher.config import ICPFlowConfig

from helpers.drives import synthetic_drive

TEACHER = ICPFlowConfig.preset("waymo", ground={"sensor_height": 1.9, "patchwork_z_offset": -1.9})


@pytest.fixture(scope="module")
def drives():
    """Two synthetic drives of 4 scans each (seeds 3 and 11), different ego motions."""
    return synthetic_drive(3, 4), synthetic_drive(11, 4)


def write_drive(folder, scans):
    """The scans as ``000000.npy`` ... (the usual names: two drives' files share them)."""
    folder.mkdir(parents=True, exist_ok=True)
    for k, scan in enumerate(scans):
        np.save(folder / f"{k:06d}.npy", scan)
    return folder


def job(folder, out_dir):
    return LabelJob(ScanSequenceDataset(folder, sensor_height=0.0), TEACHER, out_dir, "x")


def exact(labelled: LabelJob, pairs) -> bool:
    return all(
        pose_error(labelled.dataset.pair(k).ego1_from_ego0, pair.ego1_from_ego0)[0] < 0.02
        for k, pair in enumerate(pairs)
    )


def test_another_drive_with_the_same_names_gets_its_own_trajectory(tmp_path, drives):
    (first, first_scans), (second, second_scans) = drives
    out = tmp_path / "labels"
    out.mkdir()
    one = job(write_drive(tmp_path / "a", first_scans), out)
    assert drive_trajectory(one, progress=False)["reused"] == 0 and exact(one, first)
    # another folder, the same file names, into the same out_dir with overwrite=false: not reused
    two = job(write_drive(tmp_path / "b", second_scans), out)
    assert drive_trajectory(two, progress=False)["reused"] == 0 and exact(two, second)
    # the same folder rewritten with the other drive's scans (same names): not reused either
    write_drive(tmp_path / "a", second_scans)
    replaced = job(tmp_path / "a", out)
    assert drive_trajectory(replaced, progress=False)["reused"] == 0 and exact(replaced, second)
    again = job(tmp_path / "a", out)
    assert drive_trajectory(again, progress=False)["reused"] == 3  # nothing changed: reused


def test_a_touched_scan_and_overwrite_estimate_it_afresh(tmp_path, drives):
    (pairs, scans), _ = drives
    folder = write_drive(tmp_path / "scans", scans)
    out = tmp_path / "labels"
    out.mkdir()
    assert drive_trajectory(job(folder, out), progress=False)["reused"] == 0
    assert drive_trajectory(job(folder, out), progress=False)["reused"] == 3
    stat = (folder / "000002.npy").stat()
    os.utime(folder / "000002.npy", ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000_000))
    assert drive_trajectory(job(folder, out), progress=False)["reused"] == 0
    assert drive_trajectory(job(folder, out), progress=False, overwrite=True)["reused"] == 0
    assert (out / NAME).is_file()


def test_a_scan_too_small_to_register_is_no_step(tmp_path, drives, caplog):
    (pairs, scans), _ = drives
    tiny = scans[2][:5]  # 5 points mid-drive
    folder = write_drive(tmp_path / "scans", [scans[0], scans[1], tiny, scans[3]])
    labelled = job(folder, tmp_path / "labels")
    labelled.out_dir.mkdir()
    with caplog.at_level("WARNING", logger="label"):
        summary = drive_trajectory(labelled, progress=False)
    said = [record.getMessage() for record in caplog.records]
    assert summary == {"steps": 3, "reused": 0, "lost": 2}
    assert said == [
        f"000002.npy: 5 points, too few to register (at least {MIN_EGO_POINTS}); the pairs across it get no ego motion"
    ]
    assert pose_error(labelled.dataset.pair(0).ego1_from_ego0, pairs[0].ego1_from_ego0)[0] < 0.02
    for k in (1, 2):  # the pairs across the tiny scan fail, saying why
        with pytest.raises(FramePairError, match="no ego motion from"):
            labelled.dataset.pair(k)


def test_a_scan_of_one_point_repeated_is_no_step(tmp_path, drives):
    """The cousin of a tiny scan: 2,000 returns at one spot (a blocked sensor) have points enough to count but
    nothing to register; the odometry loses track there instead of chaining a step from them."""
    (pairs, scans), _ = drives
    blocked = np.tile(np.array([[5.0, 5.0, 0.5]], np.float32), (2000, 1))
    folder = write_drive(tmp_path / "scans", [scans[0], scans[1], blocked, scans[3]])
    labelled = job(folder, tmp_path / "labels")
    labelled.out_dir.mkdir()
    summary = drive_trajectory(labelled, progress=False)
    assert summary["lost"] >= 2
    assert pose_error(labelled.dataset.pair(0).ego1_from_ego0, pairs[0].ego1_from_ego0)[0] < 0.02
    for k in (1, 2):
        with pytest.raises(FramePairError, match="no ego motion from"):
            labelled.dataset.pair(k)
