"""Scene flow of raw scan files with a trained FastFlow3D: a pair (the flow and a bird's-eye-view PNG) or a stream.

    fastflow3d-infer [MODEL] SCAN0 SCAN1 [--poses FILE | --ego FILE] [--out FILE.npz|FILE.npy]
        [--bev FILE.png | --no-bev] [--rerun FILE.rrd] [--bin-columns N] [--backend onnx|pt2|torchscript]
        [--device cpu] [--runtime onnxruntime|openvino] [--threads N] [--precision auto|f32|bf16|int8]
        [--sensor-height METRES|auto] [--metadata FILE | --remove-ground yes|no]
    fastflow3d-infer [MODEL] DIR|'GLOB' [--out OUT_DIR] [--rerun FILE.rrd] [...]

Without MODEL the shipped model runs (``fastflow3d.artifact.shipped``: ``experiment=synthetic_cpu``'s student), and the
first line says so. A first path is MODEL when three paths are given, or when it is a model file (``.onnx``, ``.pt2``,
``.pt``, ``.ckpt``) or a folder holding an export's files.

Stream mode (one scan argument: a folder of scans or a quoted glob, in natural name order, ``2.bin`` before
``10.bin``: ``icpflow.datasets.file_formats.list_scans``, as ``dataset=sequence`` reads them; two scans of one name stem
are refused): the scans are one stream (``fastflow3d.inference.stream.FlowStream``: nothing given, the ego motion and
ground kept across frames), and each consecutive pair's flow is written to ``OUT_DIR/<first scan's stem>.npz`` (default
``outputs/infer/<folder>``), holding what a pair's ``.npz`` holds; a progress bar shows frames per second. An
unreadable scan is skipped with a warning naming it (the pair across it is estimated from its two scans); a pair
the stream cannot estimate (a lost track) gets no file and a warning; a stream that gives no flow at all is an error.
``OUT_DIR/stream.json`` (the manifest) says which scans, which model and options, and which outputs (also those a
stopped or failed run kept): a rerun of the same stream into OUT_DIR replaces its own outputs, the names its scans
give and nothing else; OUT_DIR holding anything else (another run's flows, a file or folder of the user's, files
without a manifest, or the input scans themselves) is refused before any work. ``--rerun`` records the whole
stream (points coloured by speed, flow arrows, the estimated trajectory) on one timeline.

MODEL: an export directory, ``.onnx``, ``.pt2``, ``.pt`` or ``.ckpt`` (``fastflow3d.inference.predictor``). Scans:
``.npz`` (array ``points`` or ``pc``), ``.npy`` (N, >= 3), ``.bin`` (float32 rows: x, y, z, reflectance as KITTI, or
``--bin-columns N`` values, x, y, z first), ``.ply`` or ``.pcd``; the first three columns are x, y, z in metres
in the sensor's own frame (``icpflow.core.frame_pair.check_points``: a transposed (3, N) array is an error). Ego motion:
``--poses`` (two world_from_ego poses, scan0's then scan1's: a text file of 12 or 16 values a line, or a
(2, 4, 4) ``.npy``), ``--ego`` (one (4, 4) ``ego1_from_ego0``: 12 or 16 values, or a ``.npy``), or neither
(estimated by KISS-ICP).
Height frame (``fastflow3d.inference.predictor``): ``--sensor-height H`` says the scans' origin is H m above the ground
(1.73 for KITTI's velodyne frame), ``auto`` estimates it from scan0; without it, scans whose ground lies more than
0.5 m from where the model's frame has it are lifted into that frame with a warning. A model trained with ground
removal gets the non-ground points of each scan, found with the teacher's ground segmentation and the settings
saved with the model; ground points of scan0 move with the ego motion. A bare ``.onnx`` / ``.pt2`` without its
``metadata.json`` is refused unless ``--metadata FILE`` (an export's metadata.json) or ``--remove-ground yes|no``
(the synthetic frame and settings, with or without ground removal) says how it was trained.
Output (default ``outputs/infer/<scan0>_flow.npz``): ``flow`` (N0, 3) float32 FULL flow (``pc0 + flow`` is in scan1's
frame), ``residual`` (ego-compensated), ``in_grid`` (the network predicted the point), ``ground0`` (left out as
ground), ``ego1_from_ego0``, ``ego_estimated``; a ``.npy`` output holds the flow alone; an output (or picture, or
recording) that is one of the input files is refused. Errors are one line on stderr, exit status 2 (130 / 143 when
Ctrl-C / SIGTERM stops it: ``icpflow.core.errors_and_signals``); a scan none of whose points the network sees (outside
its grid), a frame converted without being told, or an implausible preprocessing (over 85 % ground, under 20 % of scan0
in the grid) gets a one-line warning.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import sys
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

import icpflow
from fastflow3d.artifact.file_format import (
    FILE_NAMES,
    FORMATS,
    LEGACY_FILE_NAMES,
    LEGACY_FORMATS,
    METADATA_NAME,
    SUFFIX_FORMATS,
)
from fastflow3d.inference.model_loading import AUTO, PRECISION_CHOICES
from fastflow3d.inference.scan_files import read_raw_scan, read_transforms, refuse_input_as_output, write_flow
from fastflow3d.inference.scan_steps import MAX_SENSOR_HEIGHT, check_sensor_height
from fastflow3d.inference.stream_folder import (
    MANIFEST,
    claim_output_folder,
    output_name,
    stream_files,
    stream_manifest,
    write_manifest,
)
from icpflow.core.console import quiet, recorded_warnings
from icpflow.core.errors_and_signals import exit_status, one_line, stop_on_signals
from icpflow.core.frame_pair import FramePair
from icpflow.core.geometry import relative_transform

#: a stream's pairs in flight (``FlowStream(overlap=True, depth=...)``): with two, a pair slow on one thread holds the
#: other up less (BENCHMARKS.md, "Student latency and the stream"); the last ``STREAM_DEPTH`` flows are written after
#: the last scan is read
STREAM_DEPTH = 2


#: what a first positional path that names a model looks like (:func:`is_model`)
MODEL_SUFFIXES = (*SUFFIX_FORMATS, ".ckpt")
MODEL_FILES = (*FILE_NAMES.values(), *LEGACY_FILE_NAMES)
PROG = "fastflow3d-infer"
USAGE = f"{PROG} [MODEL] SCAN0 SCAN1 [options]  |  {PROG} [MODEL] DIR|'GLOB' [options]"
EXAMPLES = f"""examples:
  {PROG} ../shared/data/kitti_hdl64_scans --out flows/kitti   # a stream, the shipped model
  {PROG} a.bin b.bin --ego ego.txt --refine                   # one pair, its ego motion given
  {PROG} outputs/train/synthetic/export scans/ --precision f32  # a model of your own

MODEL (first, optional): an export directory, .onnx, .pt2, .pt or .ckpt; without it the shipped synthetic_cpu
student runs (its card: fastflow3d/artifact/models/synthetic_cpu/MODEL_CARD.md). Conventions, outputs and errors:
the README's "Inference" section and this module's docstring (python -m pydoc fastflow3d.inference.cli)."""


def parse_args(argv):
    """The options, with ``model`` (None: the shipped model), ``scan0`` and ``scan1`` (None: a stream) resolved."""
    parser = argparse.ArgumentParser(
        prog=PROG,
        usage=USAGE,
        description=__doc__.splitlines()[0],
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("paths", type=user_path, nargs="+", metavar="PATH", help="[MODEL] SCAN0 [SCAN1], or a stream")
    parser.add_argument("--version", action="version", version=f"{PROG} {icpflow.__version__}")
    ego = parser.add_mutually_exclusive_group()
    ego.add_argument("--poses", type=user_path, help="two world_from_ego poses (scan0, scan1)")
    ego.add_argument("--ego", type=user_path, help="one ego1_from_ego0 transform")
    parser.add_argument("--out", type=user_path, help="flow .npz/.npy (default outputs/infer/...); a stream: a folder")
    pictures = parser.add_mutually_exclusive_group()
    pictures.add_argument("--bev", type=user_path, help="BEV PNG (default: the output's name with .png)")
    pictures.add_argument("--no-bev", action="store_true", help="write no picture")
    parser.add_argument("--extent", type=float, default=40.0, help="half-width of the picture in metres")
    parser.add_argument("--rerun", type=user_path, metavar="FILE.rrd", help="also a 3D recording")
    parser.add_argument(
        "--precision",
        choices=PRECISION_CHOICES,
        default=AUTO,
        help="auto (default): int8 where the export has it and the CPU has int8 dot products, else f32",
    )
    parser.add_argument("--refine", action="store_true", help="refine the flow per object with the teacher's ICP")
    parser.add_argument(
        "--sensor-height",
        type=sensor_height,
        metavar="M|auto",
        help="the scans' origin above the ground (KITTI: 1.73), or auto",
    )
    engine = parser.add_argument_group("engine and file formats")
    engine.add_argument("--threads", type=int, help="engine threads (default: the usable cores; a stream: one fewer)")
    engine.add_argument("--runtime", choices=("onnxruntime", "openvino"), help="CPU engine for the ONNX file")
    engine.add_argument("--backend", choices=(*FORMATS, *LEGACY_FORMATS), help="format of an export directory")
    engine.add_argument("--device", default="cpu", help="torch device for .pt2, .pt and checkpoints")
    engine.add_argument(
        "--bin-columns", type=int, choices=range(3, 17), metavar="N", help="float32 values per row of a .bin scan"
    )
    bare = engine.add_mutually_exclusive_group()
    bare.add_argument("--metadata", type=user_path, help="metadata.json of a bare .onnx/.pt2 (its preprocessing)")
    bare.add_argument(
        "--remove-ground", choices=("yes", "no"), help="a bare .onnx/.pt2 without metadata: trained without ground?"
    )
    args = parser.parse_args(argv)
    try:
        args.model, args.scan0, args.scan1 = split_paths(args.paths)
    except ValueError as error:
        parser.error(str(error))
    return args


def is_model(path: Path) -> bool:
    """Whether a first positional path names a model: a model file by its suffix, or a folder holding an export's
    files (a folder of scans holds none)."""
    if path.suffix.lower() in MODEL_SUFFIXES:
        return True
    return path.is_dir() and any((path / name).exists() for name in (METADATA_NAME, *MODEL_FILES))


def split_paths(paths: list[Path]) -> tuple[Path | None, Path, Path | None]:
    """``(model, scan0, scan1)`` of the positional paths: three are MODEL SCAN0 SCAN1; of two or one, a first that
    :func:`is_model` names the model, else the shipped model runs (model None); scan1 None: a stream."""
    if len(paths) > 3:
        raise ValueError(f"at most three paths ([MODEL] SCAN0 [SCAN1]), got {len(paths)}")
    model = paths[0] if len(paths) == 3 or (len(paths) == 2 and is_model(paths[0])) else None
    scans = paths[1:] if model is not None else paths
    if len(paths) == 1 and is_model(paths[0]):
        raise ValueError(f"{paths[0]} is a model: name the scans after it ([MODEL] SCAN0 SCAN1, or a folder of scans)")
    return model, scans[0], scans[1] if len(scans) == 2 else None


def user_path(text: str) -> Path:
    """A path option as a shell would give it: a leading ``~`` is the home folder, also where the shell left it (a
    quoted ``'~/x'``, a glob), never a folder named ``~``."""
    return Path(text).expanduser()


def sensor_height(text: str):
    """``--sensor-height``: ``auto`` or metres, as ``Predictor.load`` takes them (``check_sensor_height``)."""
    if text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is neither metres nor 'auto'") from None
    try:
        check_sensor_height(value)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r}: must be 'auto' or metres above the ground in [0, {MAX_SENSOR_HEIGHT:g}]"
        ) from None
    return value


def given_preprocessing(args):
    """What ``--metadata`` / ``--remove-ground`` say about a bare exported file (None: nothing)."""
    from icpflow.scans.preprocess import Preprocessing

    if args.metadata is not None:
        return args.metadata
    if args.remove_ground is not None:
        return {"remove_ground": args.remove_ground == "yes", **Preprocessing().to_dict()}
    return None


def load_predictor(args):
    """The Predictor the options ask for (model, engine, height frame, preprocessing, refinement)."""
    from fastflow3d.inference.prediction import PredictorWarning
    from fastflow3d.inference.predictor import Predictor

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PredictorWarning)
        predictor = Predictor.load(
            args.model,
            backend=args.backend,
            device=args.device,
            runtime=args.runtime,
            threads=args.threads,
            precision=args.precision,
            sensor_height=args.sensor_height,
            preprocessing=given_preprocessing(args),
            refine=args.refine,
        )
    say_warnings(caught)  # a precision this CPU would emulate, asked for by name: its one line
    if getattr(args, "shipped", False):
        print(f"infer: model: {predictor.model_name}", file=sys.stderr)
    return predictor


def say_warnings(caught, keep=lambda message: True) -> None:
    """Each recorded ``PredictorWarning`` whose message ``keep`` accepts as an ``infer: warning:`` line; any other
    warning raised again as it was."""
    from fastflow3d.inference.prediction import PredictorWarning

    for warning in caught:
        if issubclass(warning.category, PredictorWarning):
            message = str(warning.message)
            if keep(message):
                print(f"infer: warning: {message.removeprefix('Predictor: ')}", file=sys.stderr)
        else:
            warnings.warn_explicit(warning.message, warning.category, warning.filename, warning.lineno)


def infer(args) -> tuple[Path, Path | None, str]:
    """Read, predict, write; returns the flow path, the picture path (or None) and the network's precision."""
    from fastflow3d.inference.prediction import PredictorWarning
    from icpflow.viz.pictures import plot_bev

    out = args.out or Path("outputs/infer") / f"{args.scan0.stem}_flow.npz"
    if out.suffix not in (".npz", ".npy"):
        raise ValueError(f"{out}: output must end in .npz or .npy")
    inputs = [args.scan0, args.scan1, args.model, args.poses, args.ego, args.metadata]
    bev = None if args.no_bev else args.bev or out.with_suffix(".png")
    for output in (out, bev, args.rerun):
        refuse_input_as_output(output, inputs)
    pc0, pc1 = read_raw_scan(args.scan0, args.bin_columns), read_raw_scan(args.scan1, args.bin_columns)
    ego = None
    if args.poses is not None:
        pose0, pose1 = read_transforms(args.poses, 2)
        ego = relative_transform(pose0, pose1)
    elif args.ego is not None:
        ego = read_transforms(args.ego, 1)[0]
    predictor = load_predictor(args)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PredictorWarning)
        prediction = predictor.predict(pc0, pc1, ego)
    nothing_seen = not prediction.in_grid.any()  # said below, more precisely than the implausible-grid warning
    say_warnings(caught, lambda message: not (nothing_seen and message.startswith("Predictor: implausible")))
    if nothing_seen:
        print(
            f"infer: warning: no point of {args.scan0} lies inside the model's grid (nor is it kept as non-ground): "
            "its flow is the ego motion only; are the scans in metres, in the sensor's frame?",
            file=sys.stderr,
        )
    write_flow(out, prediction)
    if args.rerun is not None:  # the 3D viewer: pc0, pc1, the flow, ground and in-grid masks
        from icpflow.viz.recording import record_pair

        ground0 = prediction.ground0 if predictor.remove_ground else None
        scans = FramePair(pc0=pc0, pc1=pc1, ego1_from_ego0=prediction.ego1_from_ego0, ground0=ground0)
        record_pair(args.rerun, scans, {"fastflow3d": prediction.flow}, prediction.in_grid)
    if bev is not None:
        pair = FramePair(
            pc0=pc0,
            pc1=pc1,
            ego1_from_ego0=prediction.ego1_from_ego0,
            ground0=prediction.ground0 if predictor.remove_ground else None,
            source=str(args.scan0),
        )
        source = (
            "estimated" if prediction.ego_estimated else "assumed (identity)" if prediction.ego_assumed else "given"
        )
        plot_bev(
            pair,
            bev,
            predicted=prediction.flow,
            extent=args.extent,
            title=f"{args.scan0.name} -> {args.scan1.name}: FastFlow3D ({predictor.backend}), ego motion {source}",
        )
    return out, bev, predictor.precision


def read_ahead(files: list[Path], columns, reader: ThreadPoolExecutor):
    """Each scan's path with the future of its read in ``reader``, the next scan's read submitted before this one is
    waited on: a scan is read while the frame before it is worked on. A lazy generator: the reads follow the loop."""
    reading = reader.submit(read_raw_scan, files[0], columns)
    for index, path in enumerate(files):
        read = reading
        if index + 1 < len(files):
            reading = reader.submit(read_raw_scan, files[index + 1], columns)
        yield path, read


class StreamOutputs:
    """What a stream writes into ``out`` as its steps come out: each pair's flow file (written in ``writer``, one at
    a time beside the next frame; its error, a full disk, raised at the next write or at :meth:`close`), the rerun
    recording (or None) and the trajectory. ``outputs``: the file names written, in order; ``failed``: the pairs
    that could not be computed (``StreamStep.failed``) and the scans that could not be read (scan0 None), each its
    scans and the reason. It keeps the points of the scans whose step is still to come (a recording draws them), none
    longer."""

    def __init__(self, out: Path, writer: ThreadPoolExecutor, recording, remove_ground: bool, depth: int):
        self.out, self.writer, self.recording = out, writer, recording
        self.remove_ground, self.depth = remove_ground, depth
        self.outputs, self.trajectory, self.scans, self.pushed, self.writing = [], [], {}, [], None
        self.failed: list[dict] = []

    def push(self, stream, source: str, read):
        """The scan of ``read`` (a future of its points) into ``stream``; its step, or None (a scan that cannot be
        read is skipped with its reason, the stream's warning)."""
        try:
            points = read.result()
        except (ValueError, OSError) as error:
            stream.skip(source, one_line(error))
            self.failed.append({"scans": [None, source], "reason": one_line(error)})
            return None
        self.scans[source] = points
        self.pushed.append(source)
        return stream.push(points, source=source)

    def write(self, step) -> None:
        """A step of the stream out: its flow file, the recording, the trajectory."""
        prediction = step.prediction
        if step.failed is not None:
            self.failed.append({"scans": [step.previous, step.source], "reason": step.failed})
        if prediction is not None:
            name = output_name(step.previous)
            self.close()  # the previous file is written first
            self.writing = self.writer.submit(write_flow, self.out / name, prediction)
            self.outputs.append(name)
            if self.recording is not None:
                pair = FramePair(
                    pc0=self.scans[step.previous],
                    pc1=self.scans[step.source],
                    ego1_from_ego0=prediction.ego1_from_ego0,
                    ground0=prediction.ground0 if self.remove_ground else None,
                    source=step.previous,
                )
                self.recording.log_pair(len(self.outputs), pair, {"fastflow3d": prediction.flow}, prediction.in_grid)
        if step.pose is not None:
            if step.restarted and prediction is None:
                self.trajectory.clear()
            self.trajectory.append(step.pose[:3, 3])
            if self.recording is not None:
                self.recording.log_trajectory(len(self.outputs), np.array(self.trajectory))
        still = (step.source, *self.pushed[-1 - self.depth :])  # this step's pc1, the scans whose step is to come
        for name in [name for name in self.scans if name not in still]:
            del self.scans[name]

    def close(self) -> None:
        """Wait for the file being written (its error raised here)."""
        writing, self.writing = self.writing, None
        if writing is not None:
            writing.result()

    def kept(self) -> list[str]:
        """The flow files that are in ``out`` (each written whole or not at all): all of ``outputs`` after a run,
        those finished before a stop."""
        return [name for name in self.outputs if (self.out / name).is_file()]


def infer_stream(args) -> tuple[Path, int, int, int, str]:
    """Stream mode (module docstring): returns the output folder, the flows written, the scans read, the pairs and
    scans that failed (the manifest lists them) and the network's precision."""
    from fastflow3d.inference.stream import FlowStream, overlap_threads
    from icpflow.core.console import Progress

    if args.poses is not None or args.ego is not None:
        raise ValueError("--poses / --ego give a pair's ego motion; a stream estimates its own (leave them out)")
    files = stream_files(args.scan0)
    out = args.out or Path("outputs/infer") / (args.scan0.name if args.scan0.is_dir() else "stream")
    if out.suffix in (".npz", ".npy"):
        raise ValueError(f"{out}: --out of a stream is a folder (one .npz per pair)")
    refuse_input_as_output(args.rerun, [*files, args.model, args.metadata])
    if args.threads is None:
        args.threads = overlap_threads()
    predictor = load_predictor(args)
    manifest = stream_manifest(args, files, predictor.precision)
    claim_output_folder(out, manifest, files)
    stream = FlowStream(predictor, overlap=True, depth=STREAM_DEPTH)  # each pair's network beside the next scans' steps
    recording = None
    if args.rerun is not None:
        from icpflow.viz.recording import PairRecording

        recording = PairRecording(args.rerun, application="fastflow3d-infer")
    sink = None
    try:
        with (
            ThreadPoolExecutor(1, thread_name_prefix="infer-writer") as writer,
            ThreadPoolExecutor(1, thread_name_prefix="infer-reader") as reader,
            Progress(total=len(files), unit="frame", desc="infer") as bar,  # its rate: frames per second
        ):
            sink = StreamOutputs(out, writer, recording, predictor.remove_ground, stream.depth)
            flush = itertools.repeat((None, None), stream.depth)  # the steps still in flight after the last scan
            for path, read in itertools.chain(read_ahead(files, args.bin_columns, reader), flush):
                with recorded_warnings() as caught:
                    step = sink.push(stream, str(path), read) if path is not None else stream.flush()
                for warning in caught:
                    bar.write(f"infer: warning: {str(warning.message).split(': ', 1)[-1]}", file=sys.stderr)
                if step is not None:
                    sink.write(step)
                if path is not None:
                    bar.update(1)
            sink.close()
    except BaseException:  # stopped or failed: the manifest lists the flows kept (each whole, or not there)
        with contextlib.suppress(Exception):  # where even it cannot be written (a full disk), the first error is said
            kept, failed = (sink.kept(), sink.failed) if sink is not None else ([], [])
            write_manifest(out, manifest, kept, complete=False, failed=failed)
        raise
    write_manifest(out, manifest, sink.outputs, complete=True, failed=sink.failed)
    written = len(sink.outputs)
    if recording is not None:
        recording.close()
    if not written:
        raise ValueError(
            f"{args.scan0}: no flow: the stream gave none of its {len(files)} scans a pair (see the warnings)"
        )
    return out, written, len(files), len(sink.failed), predictor.precision


def main(argv=None) -> int:
    """Command-line entry; returns the exit status (0 written; 2 an error, one line on stderr; 130 / 143 stopped by
    Ctrl-C / SIGTERM) as ``icpflow.core.errors_and_signals`` reports it for every entry point. A bad option exits
    (argparse)."""
    quiet()
    args = parse_args(argv)
    return exit_status("infer", lambda: _main(args), ValueError, RuntimeError)


def _main(args) -> None:
    if args.model is None:
        from fastflow3d.artifact.shipped import shipped_model

        args.model = shipped_model()
        args.shipped = True  # load_predictor names it
    if args.scan1 is None:
        with stop_on_signals():  # each flow file is written atomically: a stop leaves the pairs done, whole
            out, written, frames, failed, precision = infer_stream(args)
        rerun = f", 3D -> {args.rerun}" if args.rerun else ""
        failures = f"; {failed} failed, listed in {out / MANIFEST}" if failed else ""
        print(f"infer: {written} flows of {frames} scans -> {out}" + rerun + f" ({precision} network{failures})")
        return
    with stop_on_signals():  # the flow file is written atomically: a stop leaves none or the whole file
        out, bev, precision = infer(args)
    rerun = f", 3D -> {args.rerun}" if args.rerun else ""
    print(f"infer: flow -> {out}" + (f", BEV -> {bev}" if bev else "") + rerun + f" ({precision} network)")


if __name__ == "__main__":
    sys.exit(main())
