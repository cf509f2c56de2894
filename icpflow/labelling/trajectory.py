"""A drive without poses (``dataset=sequence`` with no poses file): its ego motion, estimated once before the
samples are labelled, in order, by one :class:`icpflow.scans.odometry.Odometry` over every scan (each with its ground,
``icpflow.scans.ground``), and handed to the reader, so that each pair is labelled with the drive's ego motion rather
than its own two scans' (a pairwise estimate has no local map and no motion model).

The steps are written beside the shards (``trajectory.npz``: ``ego1_from_ego0`` (T - 1, 4, 4) float64 per
consecutive scans, NaN where there is none; ``poses`` (done + 1, 4, 4) one pose per scan, ``track_from_scan``, and
``track`` its track; ``done``, the steps estimated; ``identity``, the scans and settings they belong to) every
``SAVE_EVERY`` steps and at the end, atomically: a rerun with the same scans and settings reuses them, a stopped run
goes on from the last saved step (whose track then starts again from that scan). A lost track or an unreadable scan
is one warning and a restart; the pairs across it get no ego motion and fail with that reason (``failures.jsonl``),
never a silent wrong pose.
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


def drive_trajectory(job, progress: bool = True) -> dict | None:
    """Estimate (or reuse) the ego motion of ``job``'s drive when its reader has no poses (the reader's
    ``drive_without_poses``), hand it to the reader (``use_ego_motions``) and return ``{"steps", "reused", "lost"}``;
    None when the reader needs none."""
    from icpflow.core.console import Progress
    from icpflow.scans.ground import GroundSegmenter
    from icpflow.scans.odometry import Odometry
    from icpflow.scans.preprocess import Preprocessing

    drive = job.dataset.drive_without_poses()
    if drive is None:
        return None
    names, read = drive
    path = job.out_dir / NAME
    settings = Preprocessing.from_teacher(job.teacher_cfg).to_dict()
    identity = json.dumps({"scans": list(names), "preprocessing": settings}, sort_keys=True)
    motions, done = np.full((len(names) - 1, 4, 4), np.nan), 0
    stored = read_trajectory(path, identity)
    if stored is not None and stored[0].shape == motions.shape:
        motions, done = stored
    reused = done
    if done < len(motions):
        segmenter, odometry = GroundSegmenter(job.teacher_cfg), Odometry(job.teacher_cfg)
        bar = Progress(total=len(motions), initial=done, unit=" scans", disable=not progress, desc="trajectory")
        try:  # scan ``done`` is read again: the first scan of this run's track
            for scan in range(done, len(names)):
                try:
                    points = read(scan)
                except (FramePairError, OSError, ValueError) as error:
                    log.warning(f"{names[scan]}: skipped ({error}); the pairs across it get no ego motion")
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
