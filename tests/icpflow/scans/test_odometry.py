"""The one odometry (icpflow.scans.odometry): a sequence of scans in, one ego motion per step out; a pair is a two-scan
sequence. Exact on the synthetic world (per drive and pairwise, the robust first step included); one normal estimate;
a lost track is a restart or no estimate, never a silent wrong pose; label.py estimates a drive without poses once,
in order, and resumes it."""

import numpy as np
import pytest

from icpflow.core.geometry import invert, pose_error
from icpflow.core.open3d_loader import load_open3d
from icpflow.scans.normals import plane_normals, smallest_axes
from icpflow.scans.odometry import NORMAL_NEIGHBOURS, Odometry, TargetPlanes, estimate_ego_motion, voxel_cloud
from icpflow.teacher.config import ICPFlowConfig

from helpers.drives import corridor, synthetic_drive

EGO = ICPFlowConfig.preset("waymo").ego_motion


@pytest.fixture(scope="module")
def moving():
    """A sequence of 8 frames whose ego drives (seed 3: about 8 m/s)."""
    pairs, scans = synthetic_drive(3, 8)
    assert np.linalg.norm(pairs[0].ego1_from_ego0[:3, 3]) > 0.3
    return pairs, scans


def test_a_drive_is_exact_on_the_synthetic_world(moving):
    """Within 2 cm and 0.05 degrees per frame (the target), the worst step within 4 cm; KISS-ICP alone (no
    refinement) is kept for comparison and is worse."""
    pairs, scans = moving
    medians = {}
    for refine in (True, False):
        odometry = Odometry(EGO, refine=refine)
        assert odometry.step(scans[0], pairs[0].ground0) is None
        steps = [odometry.step(pair.pc1, pair.ground1) for pair in pairs]
        errors = np.array([pose_error(step.ego1_from_ego0, pair.ego1_from_ego0) for pair, step in zip(pairs, steps)])
        assert not any(step.restarted for step in steps) and min(step.fitness for step in steps) > 0.8
        medians[refine] = np.median(errors[:, 0])
        if refine:
            assert medians[True] <= 0.02 and np.median(errors[:, 1]) <= 0.05 and errors[:, 0].max() <= 0.04, errors
    assert medians[True] < medians[False]


@pytest.mark.parametrize("beams, seed", [(64, 0), (32, 5)])
def test_a_pair_is_a_two_scan_sequence_and_is_exact(beams, seed):
    """The pairwise estimate (no map, no motion model: the teacher's and the Predictor's step 1 for a lone pair)
    is the two-scan sequence's, within 5 cm on every pair of a drive, the scans' ground left out."""
    pairs, _ = synthetic_drive(seed, 5, beams)
    odometry = Odometry(EGO)
    odometry.step(pairs[0].pc0, pairs[0].ground0)
    first = odometry.step(pairs[0].pc1, pairs[0].ground1).ego1_from_ego0
    for pair in pairs:
        estimate = estimate_ego_motion(pair.pc0, pair.pc1, EGO, pair.ground0, pair.ground1)
        if pair is pairs[0]:
            np.testing.assert_allclose(estimate, first, atol=1e-6)
        translation, angle = pose_error(estimate, pair.ego1_from_ego0)
        assert translation <= 0.05 and angle <= 0.1, (pair.sample_id, translation, angle)


def test_the_target_normals_are_the_nearest_points_planes(moving):
    """One normal estimate: for each moved source point its nearest target point (once each), with the normal of
    its NORMAL_NEIGHBOURS nearest target points, as open3d estimates it on the whole cloud; the whole cloud's
    normals (source None) are the same estimate."""
    from scipy.spatial import cKDTree

    o3d = load_open3d()
    pairs, scans = moving
    target = voxel_cloud(scans[1], 0.15)
    points = np.asarray(target.points)
    source = np.asarray(voxel_cloud(scans[0], 0.15).points)[::7]
    transform = pairs[0].ego1_from_ego0
    moved = source @ transform[:3, :3].T + transform[:3, 3]
    local = TargetPlanes(points).near(moved)[0]
    expected = np.unique(cKDTree(points).query(moved)[1])
    np.testing.assert_array_equal(np.asarray(local.points), points[expected])
    whole = o3d.geometry.PointCloud(target)
    whole.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(NORMAL_NEIGHBOURS))
    agree = np.abs((np.asarray(local.normals) * np.asarray(whole.normals)[expected]).sum(axis=1))
    assert np.median(agree) > 0.999 and np.mean(agree > 0.95) > 0.95
    everything = TargetPlanes(points).near()[0]
    np.testing.assert_array_equal(np.asarray(everything.points), points)
    agree = np.abs((np.asarray(everything.normals) * np.asarray(whole.normals)).sum(axis=1))
    assert np.median(agree) > 0.999 and np.mean(agree > 0.95) > 0.95


def test_sparse_far_queries_get_their_exact_neighbours_from_the_coarse_grid():
    """TargetPlanes.nearest: a query whose k-th neighbour lies beyond FINE_SHELLS cells (the sparse far rings of a
    scan) is answered on the coarse grid: the same k nearest as scipy's, whether they lie 2, 10 or 80 m away, with
    and without a reach; the dense queries never build it."""
    from scipy.spatial import cKDTree

    from icpflow.scans.odometry import FINE_SHELLS, GRID_CELL

    rng = np.random.default_rng(7)
    ground = np.column_stack([rng.uniform(-20, 20, (20000, 2)), rng.normal(0.0, 0.02, 20000)])
    radius, angle = rng.uniform(25, 90, 400), rng.uniform(0, 2 * np.pi, 400)
    far = np.column_stack([radius * np.cos(angle), radius * np.sin(angle), rng.uniform(-1, 4, 400)])  # sparse rings
    points = np.concatenate([ground, far])
    query = np.concatenate([ground[::50] + rng.normal(0, 0.05, (400, 3)), far[::4] + 0.3, [[300.0, 0.0, 0.0]]])
    tree, planes = cKDTree(points), TargetPlanes(points)
    distance, expected = tree.query(query, k=10)
    assert (distance[:, -1] > (FINE_SHELLS + 1) * GRID_CELL).sum() > 50  # these gave up on the fine grid
    got_distance, got = planes.nearest(query, 10)
    assert planes.coarse is not None and np.array_equal(got, expected)
    np.testing.assert_allclose(got_distance, distance, rtol=1e-12)
    got_distance, got = planes.nearest(query, 10, 3.0)
    within = distance < 3.0
    assert np.array_equal(got[within], expected[within]) and (got[~within] == -1).all()
    assert np.isinf(got_distance[~within]).all()
    dense = TargetPlanes(points)
    assert np.array_equal(dense.nearest(query[:100], 10)[1], expected[:100]) and dense.coarse is None


def test_the_normals_in_closed_form_are_numpys_eigenvectors():
    """``smallest_axes`` and ``plane_normals`` (icpflow.scans.normals): the eigenvector of the smallest eigenvalue, as
    numpy.linalg.eigh gives it (up to sign), on planes, lines and blobs of 10 points anywhere; (0, 0, 1) where no
    axis is defined."""
    rng = np.random.default_rng(0)
    for spread in ([1.0, 0.5, 0.01], [1.0, 0.02, 0.01], [1.0, 1.0, 1.0], [1.0, 0.3, 0.03]):
        points = rng.normal(size=(500, 10, 3)) * spread
        rotations = np.linalg.qr(rng.normal(size=(500, 3, 3)))[0]
        points = np.matmul(points, rotations.transpose(0, 2, 1)) + rng.normal(size=(500, 1, 3)) * 30
        centred = points - points.mean(axis=1, keepdims=True)
        scatter = np.matmul(centred.transpose(0, 2, 1), centred)
        expected = np.linalg.eigh(scatter)[1][:, :, 0]
        assert np.abs((smallest_axes(scatter) * expected).sum(axis=1)).min() > 1 - 1e-9
        # plane_normals: the same from the neighbourhoods' indices into a cloud, shuffled
        cloud, shuffle = points.reshape(-1, 3), rng.permutation(5000)
        neighbours = np.argsort(shuffle).reshape(500, 10)
        normals = plane_normals(np.ascontiguousarray(cloud[shuffle]), neighbours)
        assert np.abs((normals * expected).sum(axis=1)).min() > 1 - 1e-9
        np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, rtol=1e-12)
    np.testing.assert_array_equal(smallest_axes(np.zeros((2, 3, 3))), [[0, 0, 1], [0, 0, 1]])
    flat = np.ones((4, 3))  # one point four times, or two: no spread, no plane
    np.testing.assert_array_equal(plane_normals(flat, np.zeros((2, 10), np.int64)), [[0, 0, 1], [0, 0, 1]])


def test_two_places_spliced_give_no_estimate_then_a_new_exact_track(moving):
    """A jump to another place: no pose for that step (never a wrong one), then the next steps are exact."""
    pairs, scans = moving
    others, other_scans = synthetic_drive(11, 4)
    odometry = Odometry(EGO)
    for scan in scans[:3]:
        odometry.step(scan)
    lost = odometry.step(other_scans[0])
    assert lost.ego1_from_ego0 is None and lost.restarted and lost.fitness < 0.5
    for pair, scan in zip(others, other_scans[1:]):
        step = odometry.step(scan)
        assert not step.restarted and pose_error(step.ego1_from_ego0, pair.ego1_from_ego0)[0] < 0.03
    assert estimate_ego_motion(scans[0], other_scans[0], EGO) is None  # a pair that does not overlap


def test_a_track_steps_from_its_last_motion_and_registers_only_where_that_fails(moving, monkeypatch):
    """After a track's first step, a step starts from the last step's motion (constant velocity) and KISS-ICP does
    not register the scan; where the motion turns around (the scans played back), that start fails its check, and
    KISS-ICP's registration gives the start instead: every step within 3 cm of the truth, no restart."""
    pairs, scans = moving
    odometry = Odometry(EGO)
    aligned = []
    odometry.step(scans[0], pairs[0].ground0)
    odometry.step(pairs[0].pc1, pairs[0].ground1)  # the first step: KISS-ICP's registration
    align = type(odometry._kiss.registration).align_points_to_map

    def counted(self, *args, **kwargs):
        aligned.append(len(aligned))
        return align(self, *args, **kwargs)

    monkeypatch.setattr(type(odometry._kiss.registration), "align_points_to_map", counted)
    grounds = [pairs[0].ground0] + [pair.ground1 for pair in pairs]
    forth = [odometry.step(pair.pc1, pair.ground1) for pair in pairs[1:]]
    assert not aligned  # a smooth drive: no registration after the first step
    for pair, step in zip(pairs[1:], forth):
        assert not step.restarted and pose_error(step.ego1_from_ego0, pair.ego1_from_ego0)[0] < 0.03
    back = [odometry.step(scans[k], grounds[k]) for k in (len(scans) - 2, len(scans) - 3)]
    assert len(aligned) == 1  # the turn-around: the velocity start fails once, the next step follows it again
    for k, step in zip((len(pairs) - 1, len(pairs) - 2), back):
        assert not step.restarted
        assert pose_error(step.ego1_from_ego0, invert(pairs[k].ego1_from_ego0))[0] < 0.03, k


def test_the_trajectory_is_the_product_of_the_steps(moving):
    pairs, scans = moving
    odometry = Odometry(EGO)
    pose, truth = np.eye(4), np.eye(4)
    odometry.step(scans[0], pairs[0].ground0)
    for pair in pairs:
        pose = pose @ invert(odometry.step(pair.pc1, pair.ground1).ego1_from_ego0)
        truth = truth @ invert(pair.ego1_from_ego0)
    assert np.linalg.norm(pose[:3, 3] - truth[:3, 3]) < 0.02 * len(pairs)


def test_label_estimates_a_drive_once_in_order_and_resumes(tmp_path, moving, caplog):
    """``label.py dataset=sequence`` without poses: the drive's ego motion, estimated once over every scan in order,
    written beside the shards and handed to the reader. A jump to another place and an unreadable scan are each one
    warning and a restart; the pairs across them fail with that reason (never a wrong pose). A stopped run goes on
    from its last saved step; a rerun of the same scans and settings reuses the file; other settings redo it."""
    from icpflow.core.frame_pair import FramePairError
    from icpflow.datasets.scan_folder import ScanSequenceDataset
    from icpflow.labelling.job import LabelJob
    from icpflow.labelling.trajectory import NAME, drive_trajectory, read_trajectory, write_trajectory

    pairs, scans = moving
    others, other_scans = synthetic_drive(11, 4)
    folder = tmp_path / "scans"
    folder.mkdir()
    drive = [*scans[:5], *other_scans]  # 0-4 one place, 5-8 another
    for k, scan in enumerate(drive):
        np.save(folder / f"{k}.npy", scan)
    (folder / "7.npy").write_bytes(b"broken")
    teacher = ICPFlowConfig.preset("waymo", ground={"sensor_height": 1.9, "patchwork_z_offset": -1.9})
    job = LabelJob(ScanSequenceDataset(folder, sensor_height=0.0), teacher, tmp_path / "labels", "x")
    job.out_dir.mkdir()
    with caplog.at_level("WARNING", logger="label"):
        summary = drive_trajectory(job, progress=False)
    said = [record.getMessage() for record in caplog.records]
    assert summary == {"steps": 8, "reused": 0, "lost": 3}
    assert len(said) == 2 and said[0].startswith("5.npy: the odometry lost track") and "7.npy: skipped" in said[1]
    truth = [pair.ego1_from_ego0 for pair in pairs[:4]] + [None, others[0].ego1_from_ego0, None, None]
    for k, expected in enumerate(truth):
        if expected is None:  # the splice; the broken scan's pairs fail on reading it first
            reason = "5.npy: no ego motion from 4.npy" if k == 4 else "7.npy: not a .npy file"
            with pytest.raises(FramePairError, match=reason):
                job.dataset.pair(k)
        else:
            assert pose_error(job.dataset.pair(k).ego1_from_ego0, expected)[0] < 0.02, k
    path = job.out_dir / NAME
    stored = path.read_bytes()
    identity = str(np.load(path)["identity"])
    motions, done = read_trajectory(path, identity)
    assert done == 8 and np.array_equal(motions, job.dataset._motions, equal_nan=True)
    with np.load(path) as saved:  # one pose per scan, in its track's first frame; a new track after each break
        assert saved["track"].tolist() == [0, 0, 0, 0, 0, 1, 1, 2, 3]
        truth = np.linalg.inv(pairs[1].ego1_from_ego0 @ pairs[0].ego1_from_ego0)  # scan 2 in scan 0's frame
        assert np.linalg.norm(saved["poses"][2][:3, 3] - truth[:3, 3]) < 0.03

    # a rerun reuses it; a run stopped after step 3 goes on from there (its track starting again at scan 3)
    rerun = LabelJob(ScanSequenceDataset(folder, sensor_height=0.0), teacher, job.out_dir, "x")
    assert drive_trajectory(rerun, progress=False)["reused"] == 8 and path.read_bytes() == stored
    partial = motions.copy()
    partial[3:] = np.nan
    write_trajectory(path, identity, partial, 3)
    resumed = LabelJob(ScanSequenceDataset(folder, sensor_height=0.0), teacher, job.out_dir, "x")
    assert drive_trajectory(resumed, progress=False) == {"steps": 8, "reused": 3, "lost": 3}
    np.testing.assert_allclose(resumed.dataset._motions[:3], motions[:3])
    assert pose_error(resumed.dataset.pair(3).ego1_from_ego0, pairs[3].ego1_from_ego0)[0] < 0.02
    # other settings: estimated again
    other = LabelJob(ScanSequenceDataset(folder, sensor_height=0.0), teacher.replace(**{"ground.margin": 0.2}),
                     job.out_dir, "x")  # fmt: skip
    assert drive_trajectory(other, progress=False)["reused"] == 0


def test_kiss_icp_takes_the_callers_thread_limit(moving, monkeypatch):
    """KISS-ICP runs threads of its own (TBB), out of ``thread_limit``'s reach: an odometry made without ``threads``
    gives it numba's thread count where it is made, so a labelling worker's limit (the teacher's pairwise ego motion)
    holds it too; ``threads`` given wins (the stream's 1; 0: every core). The estimate is the same."""
    import numba

    from icpflow.core.threads import thread_limit
    from icpflow.scans import odometry as odometry_module

    made = []
    kiss_odometry = odometry_module.kiss_odometry
    monkeypatch.setattr(
        odometry_module, "kiss_odometry", lambda cfg, threads: made.append(threads) or kiss_odometry(cfg, threads)
    )
    pair = moving[0][0]
    free = estimate_ego_motion(pair.pc0, pair.pc1, EGO, pair.ground0, pair.ground1)
    with thread_limit(1):
        limited = estimate_ego_motion(pair.pc0, pair.pc1, EGO, pair.ground0, pair.ground1)
        for threads in (0, 2):
            Odometry(EGO, threads=threads).step(pair.pc0, pair.ground0)
    assert made == [numba.get_num_threads(), 1, 0, 2]
    np.testing.assert_allclose(limited, free, atol=1e-9)


def test_surfaces_that_leave_a_direction_free_are_said_in_one_line_and_real_ones_are_not(moving):
    import warnings

    pairs, _ = moving
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message="estimate_ego_motion")  # the synthetic world: every direction fixed
        estimate_ego_motion(pairs[0].pc0, pairs[0].pc1, EGO, pairs[0].ground0, pairs[0].ground1)
    unfixed = r"^estimate_ego_motion: the scans' surfaces do not fix the ego motion along one direction \(normal"
    with pytest.warns(UserWarning, match=unfixed) as caught:
        estimate_ego_motion(corridor(0), corridor(1, shift=0.8), EGO)
    assert "\n" not in str(caught[0].message)


def test_a_drive_says_which_steps_its_surfaces_leave_unfixed_and_a_tiny_scan_is_said(tmp_path, caplog):
    """Each step of a drive measures its normal spread: ``label.py``'s trajectory of a drive down a corridor logs one
    line per such step naming its scans; a lone pair with a scan too small to register says the identity is
    assumed."""
    from icpflow.datasets.scan_folder import ScanSequenceDataset
    from icpflow.labelling.job import LabelJob
    from icpflow.labelling.trajectory import drive_trajectory

    odometry = Odometry(EGO)
    odometry.step(corridor(0))
    steps = [odometry.step(corridor(k, shift=0.8 * k)) for k in (1, 2)]
    assert all(step.unfixed and step.spread < 0.02 for step in steps)
    folder = tmp_path / "scans"
    folder.mkdir()
    for k in range(3):
        np.save(folder / f"{k}.npy", corridor(k, shift=0.8 * k))
    teacher = ICPFlowConfig.preset("waymo")
    job = LabelJob(ScanSequenceDataset(folder, sensor_height=0.0), teacher, tmp_path / "labels", "x")
    job.out_dir.mkdir()
    with caplog.at_level("WARNING", logger="label"):
        drive_trajectory(job, progress=False)
    said = [record.getMessage() for record in caplog.records]
    assert len(said) == 2 and said[0].startswith("1.npy: from 0.npy, the scans' surfaces do not fix"), said
    with pytest.warns(UserWarning, match=r"^estimate_ego_motion: a scan of 50 points \(fewer than 100\) cannot"):
        assert np.array_equal(estimate_ego_motion(corridor(0)[:50], corridor(1), EGO), np.eye(4))
