"""The methods an evaluation scores, by name, and the frame gaps they are scored at.

A method is a callable ``method(pair, index) -> (N0, 3) float32 FULL flow`` (project convention: pc0's ego frame
of t -> positions in the ego frame of t + dt). This package's own methods:

- ``zero``: zero full flow; ``ego``: ego flow only (every point static in the world);
- ``icpflow``: the teacher (``conf/icpflow``) through :func:`icpflow.teacher.long_horizon.teacher_on_sample` (the call
  labelling makes); ``tracker=true`` chains it through the intermediate frames (``tracker=[false,true]``: one row
  each, ``icpflow`` and ``icpflow+tracker``);
- ``icpflow-raw``: the teacher on the raw scans, nothing taken from the dataset: its own ground
  (``icpflow.scans.ground``)
  and the drive's odometry (``icpflow.scans.odometry``, carried across the consecutive pairs of a log), as ``label.py``
  labels a drive without poses; beside ``icpflow`` (the dataset's ego motion and ground masks) it says what a user's
  own scans cost;
- ``shards``: the pseudo-labels a ``label.py`` run wrote (``shards=<out_dir>``), matched by sample id.

Other methods come in as factories by name (``extra``): ``eval.py`` adds ``student``
(``fastflow3d.inference.eval_methods``), so this package never imports the student.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import Any

import numpy as np

from icpflow.core.frame_pair import FramePair
from icpflow.evaluation.baselines import ego_only_flow, zero_flow

METHODS = ("zero", "ego", "icpflow", "icpflow-raw", "shards")
Method = Callable[[FramePair, int], np.ndarray]
#: a method from the run config (``eval.py``'s); raises :class:`EvaluationError` when the config does not allow it
MethodFactory = Callable[[Any], Method]


class EvaluationError(ValueError):
    """A one-line reason why the evaluation cannot start (names the option or file)."""


class TeacherMethod:
    """The ICP-Flow teacher (an ``ICPFlow``) on pairs (t, t + horizon); ``tracker``: chained through the
    intermediate frames."""

    def __init__(self, teacher, dataset, horizon: int = 1, tracker: bool = False):
        self.teacher, self.dataset, self.horizon, self.tracker = teacher, dataset, horizon, tracker

    def __call__(self, pair: FramePair, index: int) -> np.ndarray:
        from icpflow.teacher.long_horizon import teacher_on_sample

        return teacher_on_sample(self.teacher, self.dataset, index, pair, self.horizon, self.tracker).flow


class RawTeacherMethod:
    """The teacher (an ``ICPFlow``) on pairs (t, t + horizon) with nothing given: each scan's ground from the
    teacher's own segmentation, the ego motion from one ``icpflow.scans.odometry.Odometry`` across the consecutive pairs
    of a log (a pair whose pc0 is the previous pair's pc1); any other pair starts a new track. A pair the odometry gives
    no estimate (a lost track) fails, with the reason (the evaluation skips it for every method)."""

    def __init__(self, teacher, horizon: int = 1):
        from icpflow.scans.odometry import Odometry

        self.teacher, self.horizon = teacher, horizon
        self.odometry = Odometry(teacher.cfg)
        self._last: tuple | None = None  # (log, pc1, its ground masks) of the last pair

    def __call__(self, pair: FramePair, index: int) -> np.ndarray:
        last = self._last
        follows = last is not None and last[0] == pair.log_id and np.array_equal(last[1], pair.pc0)
        self._last = None  # until this pair's odometry step is done
        masks0 = last[2] if follows else self.teacher.ground.masks(pair.pc0)  # (ground, its surface)
        masks1 = self.teacher.ground.masks(pair.pc1)
        if not follows:
            self.odometry.reset()
            self.odometry.step(pair.pc0, masks0[1])
        step = self.odometry.step(pair.pc1, masks1[1])
        self._last = (pair.log_id, pair.pc1, masks1)
        ground0, ground1 = masks0[0], masks1[0]
        if step.ego1_from_ego0 is None:
            raise ValueError(f"icpflow-raw: the odometry lost track (fitness {step.fitness:.2f}); no ego motion")
        return self.teacher(
            pair.pc0,
            pair.pc1,
            step.ego1_from_ego0,
            ground0,
            ground1,
            pair.time0,
            pair.time1,
            gap=self.horizon,
            dt=pair.dt,
        ).flow


class ShardMethod:
    """Pseudo-labels stored by ``label.py``: the stored flow of the sample with the same id and the same pc0."""

    def __init__(self, out_dir):
        from icpflow.shards.reader import ShardDataset

        try:
            self.shards = ShardDataset(out_dir)
        except FileNotFoundError as error:
            raise EvaluationError(f"shards={out_dir}: {error}") from None
        self.by_id = {sample_id: i for i, sample_id in enumerate(self.shards.sample_ids)}
        if not self.by_id:
            raise EvaluationError(f"shards={out_dir}: the shards hold no samples")
        if self.shards.incomplete():  # its missing pairs are skipped and listed; why, said once here
            print(f"eval: warning: shards={self.shards.incomplete()}", file=sys.stderr)

    def __call__(self, pair: FramePair, index: int) -> np.ndarray:
        position = self.by_id.get(pair.sample_id)
        if position is None:
            raise KeyError(f"{self.shards.root}: no stored sample {pair.sample_id!r}")
        stored = self.shards[position]
        if stored["pc0"].shape != pair.pc0.shape or not np.allclose(stored["pc0"], pair.pc0, atol=1e-5):
            raise ValueError(f"{self.shards.root}: sample {pair.sample_id!r} was labelled on other points")
        return stored["flow"]


def build_methods(
    names,
    horizons=(1,),
    trackers=(False,),
    *,
    dataset=None,
    teacher_config=None,
    shards=None,
    extra: dict[str, Callable[[], Method]] | None = None,
) -> dict[int, dict[str, Method]]:
    """Per horizon k, the methods scored on pairs (t, t + k) by row name, each ``method(pair, index) -> full flow``.

    ``icpflow`` gives one row per value of ``trackers``: ``icpflow``, and ``icpflow+tracker`` when both are asked
    for. At horizon 1 the tracker has nothing to chain: both rows are then the same object (called once per pair).
    The other methods, and the teacher's ``ICPFlow``, are built once and shared by every horizon. ``extra`` gives
    the methods of other packages by name, each built by calling it (no arguments).
    """
    extra = extra or {}
    names, trackers = list(names), list(trackers)
    if not names or len(set(names)) != len(names):
        raise EvaluationError(f"method must name distinct methods, got {names}")
    if not trackers or not all(isinstance(t, bool) for t in trackers) or len(set(trackers)) != len(trackers):
        raise EvaluationError(f"tracker must be true, false or [false,true], got {trackers}")
    shared = {}
    for name in names:
        if name == "zero":
            shared[name] = lambda pair, index: zero_flow(pair)
        elif name == "ego":
            shared[name] = lambda pair, index: ego_only_flow(pair)
        elif name in ("icpflow", "icpflow-raw"):
            from icpflow.teacher import ICPFlow
            from icpflow.teacher.warmup import ensure_compiled

            ensure_compiled("eval")
            shared[name] = ICPFlow(teacher_config)
        elif name == "shards":
            if not shards:
                raise EvaluationError("method shards needs shards=<a label.py out_dir>")
            if len(horizons) > 1:
                raise EvaluationError("method shards scores the one horizon its labels were made for; give one horizon")
            shared[name] = ShardMethod(shards)
        elif name in extra:
            shared[name] = extra[name]()
        else:
            raise EvaluationError(f"unknown method {name!r}, expected one of {', '.join([*METHODS, *extra])}")
    methods = {}
    for horizon in horizons:
        row = {}
        for name in names:
            if name == "icpflow-raw":  # its own odometry per horizon: a track follows the pairs of one gap
                row[name] = RawTeacherMethod(shared[name], horizon)
                continue
            if name != "icpflow":
                row[name] = shared[name]
                continue
            direct = TeacherMethod(shared[name], dataset, horizon)
            for tracked in trackers:
                key = "icpflow+tracker" if tracked and len(trackers) > 1 else "icpflow"
                row[key] = TeacherMethod(shared[name], dataset, horizon, True) if tracked and horizon > 1 else direct
        methods[horizon] = row
    return methods


def parse_horizons(value) -> list[int]:
    """``horizon=`` as ascending distinct frame gaps: ``2``, ``[1,2,3,4]`` or ``"1..4"`` (one gap: a list of one)."""
    try:
        if isinstance(value, str) and ".." in value:
            first, last = value.split("..")
            horizons = list(range(int(first), int(last) + 1))
        else:
            horizons = [int(value)] if isinstance(value, (int, str)) else [int(k) for k in value]
    except (TypeError, ValueError):
        raise EvaluationError(f"horizon must be an integer, a list or first..last, got {value!r}") from None
    if not horizons or min(horizons) < 1 or len(set(horizons)) != len(horizons):
        raise EvaluationError(f"horizon must list distinct frame gaps >= 1, got {value!r}")
    return sorted(horizons)
