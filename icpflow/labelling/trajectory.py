"""A drive without poses (``dataset=sequence`` with no poses file): its ego motion, estimated once before the
samples are labelled, in order, by one :class:`icpflow.scans.odometry.Odometry` over every scan (each with its ground,
``icpflow.scans.ground``), and handed to the reader, so that each pair is labelled with the drive's ego motion rather
than its own two scans' (a pairwise estimate has no local map and no motion model).

The steps are written beside the shards (``trajectory.npz``: ``ego1_from_ego0`` (T - 1, 4, 4) float64 per
consecutive scans, NaN where there is none; ``poses`` (done + 1, 4, 4) one pose per scan, ``track_from_scan``, and
``track`` its track; ``done``, the steps estimated; ``identity``, the scans and settings they belong to: each scan's
absolute path, size and modification time, and the preprocessing) every ``SAVE_EVERY`` steps and at the end,
atomically: a rerun with the same scans and settings reuses them, a stopped run goes on from the last saved step
(whose track then starts again from that scan); another drive, a scan replaced or touched, other settings or
``overwrite=true`` estimate it afresh. A lost track, an unreadable scan or one too small to register
(``MIN_EGO_POINTS``) is one warning and a restart; the pairs across it get no ego motion and fail with that reason
(``failures.jsonl``), never a silent wrong pose.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from icpflow.core.atomic import atomic_path
from icpflow.core.frame_pair import FramePairError
from icpflow.datasets.file_formats import load_npz

NAME = "trajectory.npz"
#: steps between two saves of the trajectory
SAVE_EVERY = 25

log = logging.getLogger("label")


def read_trajectory(path, identity: str) -> tuple[np.ndarray, int] | None:
    """The saved steps and their count at ``path``, or None when absent, unreadable or of other scans or settings."""
    if not Path(path).is_file():
        return None
    try:  # the one bounded .npz reader: a crafted file claims no memory it does not hold
        stored = load_npz(Path(path), ("identity", "ego1_from_ego0", "done"), ())
        if str(stored["identity"]) != identity:
            return None
        return np.array(stored["ego1_from_ego0"], np.float64), int(stored["done"])
    except (OSError, KeyError, ValueError, TypeError):  # FramePairError is a ValueError: redone, as a stale one
        return None


def track_poses(motions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One pose per scan from the steps ``motions`` (T - 1, 4, 4) (NaN: none): ``poses`` (T, 4, 4) float64, each
    scan's ``track_from_scan`` (the frame of its track's first scan), and ``track`` (T,) int64, the track of each
    scan (a step without an estimate starts a new one)."""
    poses, track = np.tile(np.eye(4), (len(motions) + 1, 1, 1)), np.zeros(len(motions) + 1, np.int64)
    for step, motion in enumerate(motions):
        if np.isfinite(motion).all():
            poses[step + 1], track[step + 1] = poses[step] @ np.linalg.inv(motion), track[step]
        else:
            track[step + 1] = track[step] + 1
    return poses, track


def write_trajectory(path, identity: str, motions: np.ndarray, done: int) -> None:
    """The steps (and, for a reader of the file, :func:`track_poses`) at ``path``, atomically."""
    poses, track = track_poses(motions[:done])
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        np.savez(
            handle, identity=np.array(identity), ego1_from_ego0=motions, done=np.array(done), poses=poses, track=track
        )


def scan_identity(paths) -> list:
    """What identifies each scan file of a drive: ``[absolute path, size, modification time (ns)]`` (None for a file
    that cannot be read: it is skipped with a warning anyway)."""
    identity = []
    for path in map(Path, paths):
        try:
            stat = path.stat()
            identity.append([str(path.resolve()), stat.st_size, stat.st_mtime_ns])
        except OSError:
            identity.append([str(path.absolute()), None, None])
    return identity


def registrable(read, scan: int, name: str) -> np.ndarray | None:
    """Scan ``scan`` (``read(scan)``) to register, or None, with one warning, where it cannot be read or holds fewer
    than ``MIN_EGO_POINTS`` points (a step registered on a handful of points is noise that the rest of the drive would
    chain on)."""
    from icpflow.scans.odometry import MIN_EGO_POINTS

    try:
        points = read(scan)
    except (FramePairError, OSError, ValueError) as error:
        log.warning(f"{name}: skipped ({error}); the pairs across it get no ego motion")
        return None
    if len(points) < MIN_EGO_POINTS:
        log.warning(f"{name}: {len(points)} points, too few to register (at least {MIN_EGO_POINTS}); the pairs across "
                    "it get no ego motion")  # fmt: skip
        return None
    return points


def drive_trajectory(job, progress: bool = True, overwrite: bool = False) -> dict | None:
    """Estimate (or reuse) the ego motion of ``job``'s drive when its reader has no poses (the reader's
    ``drive_without_poses``), hand it to the reader (``use_ego_motions``) and return ``{"steps", "reused", "lost"}``;
    None when the reader needs none. ``overwrite``: a stored trajectory is never reused."""
    from icpflow.core.console import Progress
    from icpflow.scans.ground import GroundSegmenter
    from icpflow.scans.odometry import Odometry
    from icpflow.scans.preprocess import Preprocessing

    drive = job.dataset.drive_without_poses()
    if drive is None:
        return None
    paths, read = drive
    names = [Path(path).name for path in paths]
    path = job.out_dir / NAME
    settings = Preprocessing.from_teacher(job.teacher_cfg).to_dict()
    identity = json.dumps({"scans": scan_identity(paths), "preprocessing": settings}, sort_keys=True)
    motions, done = np.full((len(names) - 1, 4, 4), np.nan), 0
    stored = None if overwrite else read_trajectory(path, identity)
    if stored is not None and stored[0].shape == motions.shape:
        motions, done = stored
    reused = done
    if done < len(motions):
        segmenter, odometry = GroundSegmenter(job.teacher_cfg), Odometry(job.teacher_cfg)
        bar = Progress(total=len(motions), initial=done, unit=" scans", disable=not progress, desc="trajectory")
        try:  # scan ``done`` is read again: the first scan of this run's track
            for scan in range(done, len(names)):
                points = registrable(read, scan, names[scan])
                if points is None:
                    odometry.reset()
                else:
                    step = odometry.step(points, segmenter.masks(points)[1])  # the ground's surface left out
                    if step is not None and step.ego1_from_ego0 is None:
                        log.warning(f"{names[scan]}: the odometry lost track (fitness {step.fitness:.2f}): no ego "
                                    f"motion from {names[scan - 1]}, a new track starts here")  # fmt: skip
                    elif step is not None:
                        motions[scan - 1] = step.ego1_from_ego0
                        if step.restarted:
                            log.warning(f"{names[scan]}: the odometry lost track and started again from this pair "
                                        f"(fitness {step.fitness:.2f})")  # fmt: skip
                        if step.unfixed:
                            log.warning(f"{names[scan]}: from {names[scan - 1]}, {step.unfixed_warning()}")
                bar.update(scan - done)
                done = scan
                if done % SAVE_EVERY == 0:
                    write_trajectory(path, identity, motions, done)
        finally:
            write_trajectory(path, identity, motions, done)
            bar.close()
    job.dataset.use_ego_motions(motions)
    return {"steps": len(motions), "reused": reused, "lost": int(np.isnan(motions[:, 0, 0]).sum())}
