"""Flow of a LiDAR stream: scans in one at a time, the flow of each scan to the next out, nothing else given.

``FlowStream(predictor)`` wraps a :class:`fastflow3d.inference.predictor.Predictor`; :meth:`FlowStream.push` takes the
next scan (N, 3) (with an optional timestamp in seconds) and returns the :class:`StreamStep` of the previous scan to
this one: the same :class:`~fastflow3d.inference.prediction.Prediction` as ``predictor.predict(previous, scan)`` would
give with the ego motion and ground masks the stream estimated (FULL flow, project convention, in the previous scan's
frame). What the pairwise call recomputes for every pair, the stream keeps:

* the height frame: found on the first scan (``Predictor.frame_lift``) and checked every ``check_every`` scans
  (the ground below the sensor); a scan whose ground moved by more than ``FRAME_TOLERANCE`` (another sensor or
  frame) is warned about, lifted by its own ground, and the odometry restarts;
* the odometry (``icpflow.scans.odometry.Odometry``: one KISS-ICP across frames, each step refined against the previous
  scan's non-ground points from the last step's motion, KISS-ICP registering where that start fails), every scan
  down-sampled once;
* each scan's ground mask (``icpflow.scans.ground``, the model's settings): computed once, as pc1 of its pair, and
  reused
  as pc0 of the next (and left out of the odometry, also for a model that sees ground).

Bad streams never give a silent wrong flow: a missing or unreadable scan (:meth:`FlowStream.skip`), a time gap longer
than ``max_gap_s`` or a timestamp that does not increase restart the odometry with a warning (the pair across the gap
is estimated from its two scans alone); a scan with too few points keeps the motion model's prediction and gets the
ego flow only; a step whose fitness is under ``min_fitness`` is estimated afresh (``icpflow.scans.odometry``), and where
that fits under ``LOST_FITNESS`` too the pair gets no flow (``StreamStep.prediction`` None) and a new track starts;
a pair whose computation fails on its own (:data:`PAIR_FAILURES`: the memory a huge scan needs) gets no flow and
says why (``StreamStep.failed``).
Each case is one :class:`StreamWarning`; the other frames keep their flow.

``overlap=True`` uses the second core: the network of one pair, and its refinement, run in a worker thread while the
stream prepares the next scan (its ground and odometry step) and writes out the previous step, so the stream's own
thread does not wait beside an idle network core. The steps are the same, in the same order, one push late:
:meth:`FlowStream.push` returns the step of the scan pushed before (None for the first) and :meth:`FlowStream.flush`
the last one. With ``depth=2`` (the CLI's) two pairs are in flight and the steps come two pushes late (flush until
None): a pair slow on one thread then holds the other up less. A caller that reads its scans from files
(``fastflow3d-infer``) gains the throughput; a live caller that needs each flow at once keeps ``overlap=False``.

Threads: the network runs on one core fewer than the process has (:func:`overlap_threads`, the CLI's default: the
Predictor's ``threads``; on one thread ONNX Runtime sums the pillars quicker,
``fastflow3d.artifact.sequential_scatter``), and the stream's own steps on one thread (numba, torch, BLAS and OpenMP
limited while they run, else their idle threads spin on the network's core; KISS-ICP's registration, which runs
threads of its own, is given one by the odometry: ``Odometry(threads=1)``). Every numba kernel of both threads
releases the GIL. The worker's refinement registers its components on every usable core (:func:`_refinement_threads`):
a pair with many moving objects then takes the cores the stream's own steps leave idle while they wait for it. The
figures behind each choice: BENCHMARKS.md, "Student latency and the stream".
"""

from __future__ import annotations

import collections
import dataclasses
import warnings
from concurrent.futures import Future, ThreadPoolExecutor

import numpy as np

from fastflow3d.inference.prediction import Prediction, PredictorWarning, as_points
from fastflow3d.inference.predictor import PairResidual, Predictor, scans_frame_ego
from fastflow3d.network.contract import PreparedPair
from icpflow.core.deprecation import moved_message
from icpflow.core.errors_and_signals import one_line
from icpflow.core.threads import available_cores, thread_limit
from icpflow.scans.odometry import LOST_FITNESS, MIN_EGO_POINTS, Odometry
from icpflow.scans.preprocess import FRAME_TOLERANCE, estimate_ground_height, lift_points


def overlap_threads() -> int:
    """The network's threads in an overlapped stream: the usable cores but the one that runs the stream's own steps
    (ground, odometry, input and output) beside it. On 2 cores one network thread is quicker per frame than two
    that contend with those steps (BENCHMARKS.md, "Student latency and the stream")."""
    return max(1, available_cores() - 1)


def _refinement_threads() -> None:
    """The overlapped stream's worker: its refinement's numba kernels on every usable core (numba's setting is the
    calling thread's own; the network's engine keeps its own threads; module docstring)."""
    import numba

    numba.set_num_threads(min(available_cores(), numba.config.NUMBA_NUM_THREADS))


# What a pair's computation may raise that is the pair's alone (a scan too large for the memory left, a singular
# system): the pair gets no flow with one warning (StreamStep.failed) and the stream goes on with the next.
PAIR_FAILURES = (MemoryError, np.linalg.LinAlgError)


class StreamWarning(PredictorWarning):
    """Something in the stream was wrong (a gap, a lost track, a scan of another frame); one line, naming it."""


@dataclasses.dataclass(frozen=True)
class StreamStep:
    """The result of one pushed scan: ``prediction`` of the previous scan to this one (None: no flow for this pair:
    the first scan, or a lost track that a fresh estimate could not recover); ``source`` / ``previous``: the names
    of this scan and of the previous one (what the caller passed, e.g. the files); ``pose`` (4, 4) float64: this
    scan's pose in the current track's first frame (the trajectory; None when unknown); ``fitness`` of the ego-motion
    step (None: no step); ``restarted``: the odometry started again on this pair; ``failed``: why the pair could not
    be computed (:data:`PAIR_FAILURES`: its memory, a numerical failure), None where it was or had no pair."""

    prediction: Prediction | None
    source: str | None
    previous: str | None
    pose: np.ndarray | None
    fitness: float | None
    restarted: bool
    failed: str | None = None


@dataclasses.dataclass
class _Scan:
    points: np.ndarray  # (N, 3) float32 in the scans' own frame
    lifted: np.ndarray  # (N, 3) float32 in the model's height frame
    ground: np.ndarray  # (N,) bool: left out by the network
    odometry_ground: np.ndarray  # (N,) bool: left out by the odometry (the ground's surface, Predictor.scan_masks)
    timestamp: float | None
    source: str | None


@dataclasses.dataclass
class _Staged:
    """A pushed scan up to its network: either its finished ``step`` (no network to run: the first scan, a lost
    track) or the ``pair`` the network takes and what :meth:`Predictor.finish` needs after it."""

    step: StreamStep | None = None
    pair: PreparedPair | None = None
    run_network: bool = True
    ego_frame: np.ndarray | None = None
    lift: float = 0.0
    estimated: bool = True
    assumed: bool = False
    source: str | None = None
    previous: str | None = None
    pose: np.ndarray | None = None
    fitness: float | None = None
    restarted: bool = False
    surfaces: tuple[np.ndarray, np.ndarray] | None = None  # the two scans' ground surfaces (the refinement's)


class FlowStream:
    """See the module docstring. ``max_gap_s``: a larger time between two scans restarts the odometry (default
    0.25 s: 2.5 frames at 10 Hz); ``min_fitness``: below it a step is estimated afresh from its two scans (under
    ``icpflow.scans.odometry.LOST_FITNESS`` after that, the track is lost); ``check_every``: scans between
    checks of the height frame; ``refine_odometry``: refine each odometry step (off: KISS-ICP alone; not the
    flow's refinement, which is the Predictor's ``refine``); ``overlap``: run each pair's network beside the next
    scan's steps, the steps one push late (module docstring); ``depth``: with ``overlap``, the pairs in flight, the
    steps that many pushes late (module docstring). ``refine``: the old name of ``refine_odometry`` (until 0.3, with a
    DeprecationWarning; given, it wins)."""

    def __init__(
        self,
        predictor: Predictor,
        max_gap_s: float = 0.25,
        min_fitness: float = 0.5,
        check_every: int = 10,
        refine_odometry: bool = True,
        overlap: bool = False,
        depth: int = 1,
        *,
        refine: bool | None = None,
    ):
        if refine is not None:  # one meaning per name: Predictor.load(refine=...) refines the flow
            message = moved_message("FlowStream(refine=...)", "FlowStream(refine_odometry=...)")
            warnings.warn(message, DeprecationWarning, stacklevel=2)
            refine_odometry = refine
        self.predictor = predictor
        self.max_gap_s, self.check_every = float(max_gap_s), int(check_every)
        # overlapped: one thread for KISS-ICP too, beside the network (module docstring)
        self.odometry = Odometry(
            predictor.ego_config, min_fitness=min_fitness, refine=refine_odometry, threads=1 if overlap else None
        )
        self.lift: float | None = None
        self._previous: _Scan | None = None
        self._pose = np.eye(4)
        self._since_check = 0
        self._gap: str | None = None  # why the next pair must restart the odometry
        self.overlap = bool(overlap)
        if int(depth) < 1:
            raise ValueError(f"FlowStream: depth must be at least 1, got {depth}")
        self.depth = int(depth)
        # overlap: the pushes whose steps are not out yet, oldest first, each with its network's future
        self._pending: collections.deque[tuple[_Staged, Future | None]] = collections.deque()
        self._worker = (
            ThreadPoolExecutor(1, thread_name_prefix="flowstream", initializer=_refinement_threads)
            if self.overlap
            else None
        )
        self._pools = None  # overlap: the libraries' thread pools, found once (icpflow.core.threads.thread_limit)

    def reset(self) -> None:
        """Start again: the next scan begins a new stream (height frame, odometry, trajectory). With ``overlap``, a
        step not yet returned is dropped (call :meth:`flush` until None first to keep them)."""
        for _, future in self._pending:
            if future is not None:
                future.result()  # let its network finish: the worker is free for the next stream
        self._pending.clear()
        self.odometry.reset()
        self.lift, self._previous, self._pose, self._since_check, self._gap = None, None, np.eye(4), 0, None

    def skip(self, source: str, reason: str) -> None:
        """A scan of the stream could not be read (``source`` names it): one warning; the pair across it is
        estimated from its two scans alone (the odometry restarts)."""
        self._warn(f"{source}: skipped ({reason}); the next pair spans the gap, the odometry restarts")
        self._gap = "a skipped scan"

    def push(self, scan, timestamp: float | None = None, source: str | None = None) -> StreamStep | None:
        """Take the next scan (N, 3) (``timestamp`` in seconds, ``source`` its name); see :class:`StreamStep`. With
        ``overlap``: the step of the scan pushed ``depth`` pushes before this one (None for the first ``depth``
        pushes; :meth:`flush`)."""
        self.predictor.prepare_kernels()
        if not self.overlap:
            staged = self._stage(scan, timestamp, source)
            return self._complete(staged, None if staged.step is not None else self._residual(staged))
        with self._own_steps():
            staged = self._stage(scan, timestamp, source)
            future = None if staged.step is not None else self._worker.submit(self._residual, staged)
            self._pending.append((staged, future))
            return None if len(self._pending) <= self.depth else self._complete_oldest()

    def flush(self) -> StreamStep | None:
        """With ``overlap``: the oldest step not yet returned (call it until None: ``depth`` steps are left after the
        last push); without, None."""
        if not self._pending:
            return None
        with self._own_steps():
            return self._complete_oldest()

    def _complete_oldest(self) -> StreamStep:
        """With ``overlap``: the :class:`StreamStep` of the oldest pending push, once its network is done."""
        staged, future = self._pending.popleft()
        return self._complete(staged, None if future is None else future.result())

    def _own_steps(self):
        """With ``overlap``: the context of the stream's own steps (ground, odometry, input, output) on
        this thread: one thread each for numba, torch, BLAS and OpenMP, whose idle pool threads would otherwise spin on
        the core the network runs on (``icpflow.core.threads``; the network's engine keeps its own threads)."""
        from threadpoolctl import ThreadpoolController

        if self._pools is None:
            self._pools = ThreadpoolController()
        return thread_limit(1, controller=self._pools)

    def _residual(self, staged: _Staged) -> PairResidual | Exception:
        """A staged pair's network and refinement (``Predictor.pair_residual``): with ``overlap``, in the worker; the
        error where it fails (:data:`PAIR_FAILURES`)."""
        try:
            return self.predictor.pair_residual(staged.pair, staged.surfaces, staged.run_network)
        except PAIR_FAILURES as error:  # returned, not raised: the pair's step says it (_complete)
            return error

    def _complete(self, staged: _Staged, residual: PairResidual | None) -> StreamStep:
        """The :class:`StreamStep` of a staged scan, from its pair's ``residual`` (:meth:`_residual`)."""
        if staged.step is not None:
            return staged.step
        try:
            if isinstance(residual, Exception):
                raise residual
            prediction = self.predictor.finish(
                staged.pair, residual, staged.ego_frame, staged.lift, staged.estimated, staged.assumed
            )
        except PAIR_FAILURES as error:  # the odometry's step stands: the pose is kept, the track goes on
            return self._failed(staged.source, staged.previous, error, staged.pose, staged.fitness, staged.restarted)
        return StreamStep(prediction, staged.source, staged.previous, staged.pose, staged.fitness, staged.restarted)

    def _failed(self, source, previous, error, pose=None, fitness=None, restarted=True) -> StreamStep:
        """The step of a pair whose computation raised ``error`` (:data:`PAIR_FAILURES`): no flow, one warning."""
        reason = one_line(error) or type(error).__name__
        self._warn(f"{source or 'scan'}: no flow for its pair, which could not be computed ({reason})")
        return StreamStep(None, source, previous, pose, fitness, restarted, failed=reason)

    def _stage(self, scan, timestamp: float | None, source: str | None) -> _Staged:
        """Everything of a pushed scan up to its pair's network (see :class:`_Staged`), in push order. Where that
        fails (:data:`PAIR_FAILURES`) the pair gets no flow and the next pair restarts the odometry from the last
        scan that was prepared whole."""
        points = as_points(source or "scan", scan)
        previous = self._previous
        try:
            return self._stage_points(points, timestamp, source)
        except PAIR_FAILURES as error:
            self._gap = "a pair that could not be computed"
            return _Staged(self._failed(source, None if previous is None else previous.source, error))

    def _stage_points(self, points: np.ndarray, timestamp: float | None, source: str | None) -> _Staged:
        """:meth:`_stage` of a scan's checked points."""
        if self.lift is None:
            self.lift = self.predictor.frame_lift(points)
        else:
            self._check_frame(points, source)
        previous = self._previous
        if previous is not None and timestamp is not None and previous.timestamp is not None:
            gap = float(timestamp) - previous.timestamp
            if gap <= 0:
                self._warn(
                    f"{source or 'scan'}: timestamp {timestamp} does not follow {previous.timestamp}; the "
                    "odometry restarts"
                )
                self._gap = "a timestamp going backwards"
            elif gap > self.max_gap_s:
                self._warn(
                    f"{source or 'scan'}: {gap:.3f} s after the previous scan (more than {self.max_gap_s} s); "
                    "the odometry restarts"
                )
                self._gap = "a time gap"
        lifted = lift_points(points, self.lift)
        ground, odometry_ground = self.predictor.scan_masks("ground", lifted, None)
        current = _Scan(
            points, lifted, ground, odometry_ground, None if timestamp is None else float(timestamp), source
        )
        self._previous = current
        if previous is None:
            self.odometry.reset()
            self.odometry.step(lifted, odometry_ground)
            self._pose = np.eye(4)
            return _Staged(StreamStep(None, source, None, self._pose.copy(), None, False))
        if self._gap is not None:
            self.odometry.reset()
            self.odometry.step(previous.lifted, previous.odometry_ground)
            self._gap = None
            forced = True
        else:
            forced = False
        if len(points) < MIN_EGO_POINTS or len(previous.points) < MIN_EGO_POINTS:
            return self._too_few(previous, current)
        step = self.odometry.step(lifted, odometry_ground)
        restarted = forced or step.restarted
        if step.ego1_from_ego0 is None:
            self._warn(
                f"{source or 'scan'}: lost track (fitness {step.fitness:.2f} after a fresh estimate, under "
                f"{LOST_FITNESS}); no flow for this pair, a new track starts here"
            )
            self._pose = np.eye(4)
            return _Staged(StreamStep(None, source, previous.source, None, step.fitness, True))
        if step.restarted and not forced:
            self._warn(f"{source or 'scan'}: the odometry lost track and restarted (fitness {step.fitness:.2f})")
        if step.unfixed:
            self._warn(f"{source or 'scan'}: {step.unfixed_warning()}")
        ego, lift = step.ego1_from_ego0, float(self.lift)
        pair = self.predictor.network_input((previous.lifted, lifted), ego, previous.ground, ground)
        self._pose = self._pose @ np.linalg.inv(scans_frame_ego(ego, lift))
        return _Staged(
            pair=pair,
            ego_frame=ego,
            lift=lift,
            source=source,
            previous=previous.source,
            pose=self._pose.copy(),
            fitness=step.fitness,
            restarted=restarted,
            surfaces=(previous.odometry_ground, odometry_ground),
        )

    def _too_few(self, previous: _Scan, current: _Scan) -> _Staged:
        """A pair with a scan of fewer than ``MIN_EGO_POINTS`` points: the ego flow of the identity; one warning
        for the scan (as pc1 of its first pair; its second pair is said by the first); the next pair restarts the
        odometry."""
        if len(current.points) < MIN_EGO_POINTS:
            self._warn(
                f"{current.source or 'scan'}: {len(current.points)} points, too few to estimate the ego motion (at "
                f"least {MIN_EGO_POINTS}): the identity is assumed for its pairs (ego flow only), the odometry "
                "restarts"
            )
        self._gap = "too few points"
        pair = self.predictor.network_input(
            (previous.lifted, current.lifted), np.eye(4), previous.ground, current.ground
        )
        return _Staged(
            pair=pair,
            run_network=False,
            ego_frame=np.eye(4),
            lift=float(self.lift),
            estimated=False,
            assumed=True,
            source=current.source,
            previous=previous.source,
            restarted=True,
        )

    def _check_frame(self, points: np.ndarray, source: str | None) -> None:
        """Every ``check_every`` scans: is the ground still where the height frame has it? If not, warn, take
        this scan's lift and restart the odometry."""
        self._since_check += 1
        if self._since_check < self.check_every:
            return
        self._since_check = 0
        ground = estimate_ground_height(points)
        if ground is None:
            return
        lift = self.predictor.preprocessing.frame.ground_z - ground
        if abs(lift - self.lift) > FRAME_TOLERANCE:
            self._warn(
                f"{source or 'scan'}: the ground moved by {lift - self.lift:+.2f} m against the stream's height frame "
                "(another sensor or frame?); lifted by its own ground from here, the odometry restarts"
            )
            self.lift, self._gap = lift, "another frame"
            if self._previous is not None:  # the previous scan in the new frame, for the pair across the change
                prev = self._previous
                prev.lifted = lift_points(prev.points, lift)

    @staticmethod
    def _warn(message: str) -> None:
        warnings.warn(f"FlowStream: {message}", StreamWarning, stacklevel=3)
