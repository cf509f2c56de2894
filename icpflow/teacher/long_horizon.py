"""Step 11: long horizon, flow from scan 0 to scan k (k <= ``pairing.max_frame_gap``) of a sequence.

* ``direct``: one teacher call on (scan 0, scan k) with the composed ego motion; the search window is scaled by k.
* ``tracker`` (the paper's "Ours+Tracker"): teacher calls on every consecutive pair (i, i + 1); a pc0 cluster
  is followed through the intermediate scans (its match in scan i + 1 is continued by the scan-(i + 1) cluster
  holding most of that match's points) and the per-step motions ``T_cluster_i @ T_ego_i`` are composed. Points
  whose chain breaks (no cluster, no match at some step) take the direct (0, k) result. Confidence of a chained
  point is the smallest match confidence along its chain.

Scans are (N_i, 3) float32 in their own ego frames; ``ego_transforms[i]`` is ``ego{i+1}_from_ego{i}`` (4, 4) or
None (estimated); optional ``times[i]`` (N_i,) per-point capture times (s after scan i's timestamp) and ``dts[i]``
seconds between scans i and i + 1 feed the teacher's de-skew step (``teacher.deskew``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class HorizonResult:
    """Flow (N0, 3) float32 full flow from scan 0 to scan k, confidence (N0,) float32, ``chained`` (N0,) bool
    (tracker mode: the flow came from a complete chain), ``ego_k_from_0`` (4, 4) float64."""

    flow: np.ndarray
    confidence: np.ndarray
    chained: np.ndarray
    ego_k_from_0: np.ndarray


def long_horizon_flow(
    teacher, scans, ego_transforms=None, grounds=None, mode: str = "direct", times=None, dts=None
) -> HorizonResult:
    """Flow from ``scans[0]`` to ``scans[-1]`` (see the module docstring), ``mode`` "direct" or "tracker"."""
    k = len(scans) - 1
    if mode not in ("direct", "tracker"):
        raise ValueError(f"long_horizon_flow: mode must be 'direct' or 'tracker', got {mode!r}")
    max_gap = teacher.cfg.pairing.max_frame_gap
    if not 1 <= k <= max_gap:
        raise ValueError(f"long_horizon_flow: need 2 to {max_gap + 1} scans, got {len(scans)}")
    egos = list(ego_transforms) if ego_transforms is not None else [None] * k
    grounds = list(grounds) if grounds is not None else [None] * (k + 1)
    times = list(times) if times is not None else [None] * (k + 1)
    dts = list(dts) if dts is not None else [None] * k
    if len(egos) != k or len(grounds) != k + 1 or len(times) != k + 1 or len(dts) != k:
        raise ValueError(
            f"long_horizon_flow: {k + 1} scans need {k} ego transforms, {k + 1} ground masks, "
            f"{k + 1} time arrays and {k} dts"
        )

    steps = []
    if mode == "tracker" or any(e is None for e in egos):
        for i in range(k):
            steps.append(
                teacher(scans[i], scans[i + 1], egos[i], grounds[i], grounds[i + 1], times[i], times[i + 1], dt=dts[i])
            )
        egos = [step.ego1_from_ego0 for step in steps]
    ego_k = np.eye(4)
    for ego in egos:
        ego_k = np.asarray(ego, np.float64) @ ego_k
    dt_k = sum(dts) if all(dt is not None for dt in dts) else None
    direct = teacher(scans[0], scans[k], ego_k, grounds[0], grounds[k], times[0], times[k], gap=k, dt=dt_k)
    if mode == "direct":
        return HorizonResult(direct.flow, direct.confidence, np.zeros(len(scans[0]), bool), ego_k)

    motion, confidence, alive = _chain(steps, len(scans[0]))
    flow = direct.flow.copy()
    conf = direct.confidence.copy()
    points = np.asarray(scans[0], np.float64)[alive]
    moved = np.einsum("nij,nj->ni", motion[alive, :3, :3], points) + motion[alive, :3, 3]
    flow[alive] = (moved - points).astype(np.float32)
    conf[alive] = confidence[alive]
    return HorizonResult(flow, conf, alive, ego_k)


def _chain(steps, n0: int):
    """Per pc0 point: composed motion (N0, 4, 4) ego_k_from_0 along its cluster chain, chain confidence (N0,),
    and whether the chain is complete (N0,) bool."""
    motion = np.tile(np.eye(4), (n0, 1, 1))
    confidence = np.ones(n0, dtype=np.float32)
    current = steps[0].labels0.copy()  # the chained cluster of each pc0 point in the current step's pc0 labels
    alive = current >= 0
    for i, step in enumerate(steps):
        lookup = {int(s): m for m, s in enumerate(step.pairs[:, 0])}
        next_cluster = np.full(n0, -1, dtype=np.int64)
        for cluster in np.unique(current[alive]):
            rows = np.flatnonzero(alive & (current == cluster))
            m = lookup.get(int(cluster))
            if m is None:
                alive[rows] = False
                continue
            motion[rows] = step.transforms[m] @ step.ego1_from_ego0 @ motion[rows]
            confidence[rows] = np.minimum(confidence[rows], step.match_confidence[m])
            if i + 1 < len(steps):
                # the match's points in scan i + 1, and the cluster they mostly belong to in the next step
                members = steps[i + 1].labels0[step.labels1 == step.pairs[m, 1]]
                members = members[members >= 0]
                if len(members) == 0:
                    alive[rows] = False
                    continue
                next_cluster[rows] = np.bincount(members).argmax()
        current = next_cluster
    return motion, confidence, alive


def sample_tracker_flow(teacher, dataset, index: int, horizon: int, pair=None) -> HorizonResult:
    """Tracker mode on sample ``index`` of a reader (``icpflow.datasets.base.PairDataset``): the pairs
    (t, t + j), j = 1 .. ``horizon``, chained with each scan's ground masks and per-point times and the seconds
    between consecutive scans; ``pair`` is ``dataset.pair(index, horizon)`` when the caller already has it."""
    pair = dataset.pair(index, horizon=horizon) if pair is None else pair
    steps = [dataset.pair(index, horizon=j) for j in range(1, horizon)] + [pair]
    if any(not np.array_equal(step.pc0, pair.pc0) for step in steps):
        raise ValueError(f"tracker: the pairs (t, t + j), j < {horizon}, of this sample do not start at the same scan")
    scans = [pair.pc0] + [step.pc1 for step in steps]
    grounds = [pair.ground0] + [step.ground1 for step in steps]
    if any(g is None for g in grounds):
        grounds = None
    times = [pair.time0] + [step.time1 for step in steps]
    if any(t is None for t in times):
        times = None
    dts = [steps[0].dt] + [later.dt - earlier.dt for earlier, later in zip(steps, steps[1:])]
    egos, previous = None, np.eye(4)
    if all(step.ego1_from_ego0 is not None for step in steps):
        egos = []
        for step in steps:
            egos.append(step.ego1_from_ego0 @ np.linalg.inv(previous))
            previous = step.ego1_from_ego0
    return long_horizon_flow(teacher, scans, egos, grounds, mode="tracker", times=times, dts=dts)


@dataclass
class SampleFlow:
    """The teacher's labels of one sample (t, t + horizon): ``flow`` (N0, 3) float32 full flow in the ego frame of
    t + horizon, ``confidence`` (N0,) float32, ``ego1_from_ego0`` (4, 4) float64 (ego of t + horizon from ego of t),
    ``cluster`` (N0,) int32 pc0 cluster ids (-1: none; all -1 in tracker mode, whose chains span several
    clusterings), ``ground0`` (N0,) and ``ground1`` (N1,) bool ground masks (the pair's own in tracker mode, all
    False where it has none)."""

    flow: np.ndarray
    confidence: np.ndarray
    ego1_from_ego0: np.ndarray
    cluster: np.ndarray
    ground0: np.ndarray
    ground1: np.ndarray


def teacher_on_sample(teacher, dataset, index: int, pair, horizon: int, tracker: bool) -> SampleFlow:
    """The teacher on sample ``index`` of a reader, whose pair (t, t + ``horizon``) ``pair`` the caller has read:
    one call with the pair's ego motion, ground masks and point times, or (``tracker`` and ``horizon`` > 1) the
    consecutive pairs chained (:func:`sample_tracker_flow`). The one place labelling and evaluation run it."""
    if tracker and horizon > 1:
        result = sample_tracker_flow(teacher, dataset, index, horizon, pair)
        no_ground0, no_ground1 = np.zeros(len(pair.pc0), bool), np.zeros(len(pair.pc1), bool)
        return SampleFlow(
            flow=np.asarray(result.flow, np.float32),
            confidence=np.asarray(result.confidence, np.float32),
            ego1_from_ego0=np.asarray(result.ego_k_from_0, np.float64),
            cluster=np.full(len(pair.pc0), -1, np.int32),
            ground0=np.asarray(pair.ground0 if pair.ground0 is not None else no_ground0, bool),
            ground1=np.asarray(pair.ground1 if pair.ground1 is not None else no_ground1, bool),
        )
    result = teacher(
        pair.pc0,
        pair.pc1,
        ego1_from_ego0=pair.ego1_from_ego0,
        ground0=pair.ground0,
        ground1=pair.ground1,
        time0=pair.time0,
        time1=pair.time1,
        gap=horizon,
        dt=pair.dt,
    )
    return SampleFlow(
        flow=np.asarray(result.flow, np.float32),
        confidence=np.asarray(result.confidence, np.float32),
        ego1_from_ego0=np.asarray(result.ego1_from_ego0, np.float64),
        cluster=np.asarray(result.labels0, np.int32),
        ground0=np.asarray(result.ground0, bool),
        ground1=np.asarray(result.ground1, bool),
    )


__all__ = ["HorizonResult", "SampleFlow", "long_horizon_flow", "sample_tracker_flow", "teacher_on_sample"]
