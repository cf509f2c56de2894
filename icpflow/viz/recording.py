"""3D recordings of frame pairs and their flow for the rerun viewer (``rerun-sdk``, the optional ``viz`` extra).

A recording is one ``.rrd`` file (open it with ``rerun file.rrd``, the viewer that comes with the package) holding
any number of pairs on the timeline ``pair`` (0, 1, ...: consecutive samples of a sequence play as a sequence).
Per pair, every entity in the ego frame of t + dt (pc1's frame, as the BEV pictures), under ``prefix`` when given:

- ``pc0`` (N0, 3): pc0 moved by the ego motion, blue; ``pc1`` (N1, 3): red;
- ``flow/<method>/moved``: pc0 + the method's FULL flow, and ``flow/<method>/vectors``: arrows from the
  ego-compensated pc0 to pc0 + flow (points whose residual speed is at least ``min_speed`` m/s), both coloured by
  the residual (ego-compensated) speed, ``SPEED_COLOURMAP`` from 0 to ``max_speed`` m/s; one entity per method,
  ``ground_truth`` among them when the pair has it;
- ``masks/ground0``: pc0's ground points, grey, and ``masks/in_grid``: the points a network predicted (the rest
  get the ego flow), yellow: each a toggle in the viewer's entity tree;
- ``info``: the sample id, dt and the methods, as text.

The recording is kept in memory and written when closed, by Python under a temporary name then renamed
(``icpflow.core.atomic``): a run that fails leaves no half file, and a place that cannot hold the file (read-only, full)
is one ``WriteError`` naming ``path`` (rerun's own file sink, when its disk fills, logs from its writer thread and may
leave ``flush`` waiting for ever). ``rerun`` is imported on first use, with its Rust log lines off (``RUST_LOG=off``
unless the user set ``RUST_LOG``); without it :class:`ViewerUnavailable` says how to install it.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from icpflow.core.atomic import atomic_path
from icpflow.core.frame_pair import FramePair
from icpflow.core.geometry import full_to_residual, transform_points
from icpflow.core.stops import raise_stop_behind

#: matplotlib colour map of the residual speed, 0 (dark) to ``max_speed`` (bright)
SPEED_COLOURMAP = "turbo"
PC0_RGB, PC1_RGB, GROUND_RGB, IN_GRID_RGB = (31, 119, 180), (214, 39, 40), (160, 160, 160), (230, 200, 30)
#: viewers this module records for (``eval.py viewer=...``)
VIEWERS = ("rerun",)


class ViewerUnavailable(RuntimeError):
    """The rerun package is not installed. The message is one line."""


def import_rerun():
    """The ``rerun`` module, or :class:`ViewerUnavailable` naming the extra that installs it."""
    os.environ.setdefault("RUST_LOG", "off")  # read when the Rust side starts; errors come back as exceptions
    try:
        import rerun
    except ImportError as error:
        raise_stop_behind(error)
        raise ViewerUnavailable(
            "the 3D viewer needs the rerun-sdk package: pip install 'icpflow[viz]' (or pip install rerun-sdk)"
        ) from None
    return rerun


def speed_colours(speed: np.ndarray, max_speed: float = 10.0) -> np.ndarray:
    """(N, 3) uint8 RGB of (N,) speeds in m/s: ``SPEED_COLOURMAP`` over [0, ``max_speed``], clipped."""
    from matplotlib import colormaps

    rgb = colormaps[SPEED_COLOURMAP](np.clip(np.asarray(speed, np.float64) / max_speed, 0.0, 1.0))[:, :3]
    return np.round(rgb * 255).astype(np.uint8)


class PairRecording:
    """A ``.rrd`` file of frame pairs and their flows (see the module docstring); a context manager, or call
    :meth:`close` (:meth:`abort` drops the file)."""

    def __init__(
        self,
        path: str | os.PathLike,
        application: str = "icpflow",
        max_speed: float = 10.0,
        min_speed: float = 0.5,
        radius: float = 0.04,
    ) -> None:
        rr = import_rerun()
        self.rr, self.path = rr, Path(path)
        self.max_speed, self.min_speed, self.radius = float(max_speed), float(min_speed), float(radius)
        self.stream = rr.RecordingStream(application)
        self._memory = self.stream.memory_recording()
        self.pairs = 0

    def log_pair(
        self,
        step: int,
        pair: FramePair,
        flows: dict[str, np.ndarray],
        in_grid: np.ndarray | None = None,
        prefix: str = "",
    ) -> None:
        """Record ``pair`` at ``step`` of the ``pair`` timeline: its scans, each method's (N0, 3) FULL flow in
        ``flows`` (plus the ground truth when the pair has it), its ground mask and the (N0,) bool ``in_grid``."""
        rr, stream = self.rr, self.stream
        base = prefix.strip("/") + "/" if prefix.strip("/") else ""
        stream.set_time("pair", sequence=int(step))
        ego = pair.ego1_from_ego0 if pair.ego1_from_ego0 is not None else np.eye(4)
        moved = transform_points(ego, pair.pc0)
        stream.log(f"{base}pc0", rr.Points3D(moved, colors=PC0_RGB, radii=self.radius))
        stream.log(f"{base}pc1", rr.Points3D(pair.pc1, colors=PC1_RGB, radii=self.radius))
        methods = dict(flows)
        if pair.flow is not None and "ground_truth" not in methods:
            methods["ground_truth"] = pair.flow
        for name, flow in methods.items():
            flow = np.asarray(flow, np.float32)
            speed = np.linalg.norm(full_to_residual(flow, pair.pc0, ego), axis=1) / float(pair.dt)
            colours = speed_colours(speed, self.max_speed)
            moving = speed >= self.min_speed
            target = pair.pc0 + flow
            stream.log(f"{base}flow/{name}/moved", rr.Points3D(target, colors=colours, radii=self.radius))
            stream.log(
                f"{base}flow/{name}/vectors",
                rr.Arrows3D(origins=moved[moving], vectors=(target - moved)[moving], colors=colours[moving]),
            )
        if pair.ground0 is not None:
            stream.log(f"{base}masks/ground0", rr.Points3D(moved[pair.ground0], colors=GROUND_RGB, radii=self.radius))
        if in_grid is not None:
            inside = np.asarray(in_grid, bool)
            stream.log(f"{base}masks/in_grid", rr.Points3D(moved[inside], colors=IN_GRID_RGB, radii=self.radius))
        stream.log(
            f"{base}info",
            rr.TextDocument(
                f"sample {pair.sample_id or pair.source or step}, dt {pair.dt:.3f} s, methods: {', '.join(methods)}; "
                f"colour = residual speed, 0 to {self.max_speed:g} m/s ({SPEED_COLOURMAP})"
            ),
        )
        self.pairs += 1

    def log_trajectory(self, step: int, positions: np.ndarray) -> None:
        """The ego trajectory so far, (K, 3) positions in the first scan's frame, at ``step`` of the ``pair``
        timeline (a stream's recording)."""
        self.stream.set_time("pair", sequence=int(step))
        self.stream.log("trajectory", self.rr.LineStrips3D([np.asarray(positions, np.float32)], colors=PC0_RGB))

    def close(self) -> Path:
        """Write the file and put it in place; returns its path (``WriteError`` naming it where the place is full or
        read-only; nothing is left there then)."""
        self.stream.flush()
        data = self._memory.drain_as_bytes()
        self.stream.disconnect()
        with atomic_path(self.path, make_parents=True) as temporary:
            temporary.write_bytes(data)
        return self.path

    def abort(self) -> None:
        """Drop the recording (nothing is written at ``path``)."""
        self.stream.disconnect()

    def __enter__(self) -> PairRecording:
        return self

    def __exit__(self, kind, error, trace) -> None:
        if kind is None:
            self.close()
        else:
            self.abort()


def check_viewer(value) -> str | None:
    """``eval.py viewer=``: None (no recording) or ``rerun`` (the schema, ``icpflow.evaluation.options``, allows no
    other),
    which must be installed (:class:`ViewerUnavailable` otherwise)."""
    if value is None:
        return None
    import_rerun()
    return value


def record_pair(
    path: str | os.PathLike, pair: FramePair, flows: dict[str, np.ndarray], in_grid: np.ndarray | None = None
) -> Path:
    """One pair in its own ``.rrd`` file (``fastflow3d-infer --rerun``); returns the path."""
    with PairRecording(path) as recording:
        recording.log_pair(0, pair, flows, in_grid)
    return recording.path
