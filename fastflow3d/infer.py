"""Scene flow of two raw scan files with a trained FastFlow3D; writes the flow and a bird's-eye-view PNG.

    python -m fastflow3d.infer MODEL SCAN0 SCAN1 [--poses FILE | --ego FILE] [--out FILE.npz|FILE.npy]
        [--bev FILE.png | --no-bev] [--rerun FILE.rrd] [--bin-columns N] [--backend onnx|pt2|torchscript] [--device cpu]
        [--runtime onnxruntime|openvino] [--threads N]

MODEL: an export directory, ``.onnx``, ``.pt2``, ``.pt`` or ``.ckpt`` (``fastflow3d.predictor``). Scans: ``.npz``
(array ``points`` or ``pc``), ``.npy`` (N, >= 3), ``.bin`` (float32 rows: x, y, z, reflectance as KITTI, or
``--bin-columns N`` values, x, y, z first), ``.ply`` or ``.pcd``; the first three columns are x, y, z in metres
in the sensor's own frame (``icpflow.frames.check_points``: a transposed (3, N) array is an error). Ego motion:
``--poses`` (two world_from_ego poses, scan0's then scan1's: a text file of 12 or 16 values a line, or a
(2, 4, 4) ``.npy``), ``--ego`` (one (4, 4) ``ego1_from_ego0``: 12 or 16 values, or a ``.npy``), or neither
(estimated by KISS-ICP).
A model trained with ground removal gets the non-ground points of each scan, found with the teacher's ground
segmentation and the settings saved with the model (``fastflow3d.predictor``); ground points of scan0 move with the
ego motion. Output (default ``outputs/infer/<scan0>_flow.npz``): ``flow`` (N0, 3) float32 FULL flow (``pc0 + flow``
is in scan1's frame), ``residual`` (ego-compensated), ``in_grid`` (the network predicted the point), ``ground0``
(left out as ground), ``ego1_from_ego0``, ``ego_estimated``; a ``.npy`` output holds the flow alone. Errors are one
line on stderr, exit status 2; a scan none of whose points the network sees (outside its grid) gets a warning.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from fastflow3d.artifact import FORMATS, LEGACY_FORMATS
from icpflow.atomic import atomic_path
from icpflow.console import quiet
from icpflow.datasets.io import SCAN_SUFFIXES, fail, load_npz, read_poses, read_scan
from icpflow.entry import os_error_line
from icpflow.frames import FramePair, check_points
from icpflow.geometry import relative_transform, rigid_problem

NPZ_KEYS = ("points", "pc")


def read_raw_scan(path: Path, bin_columns: int | None = None) -> np.ndarray:
    """(N, 3) float32 points of one scan file (see the module docstring for the formats; ``bin_columns``: float32
    values per row of a ``.bin``, see ``icpflow.datasets.io.read_bin``)."""
    suffix = path.suffix.lower()
    if suffix != ".npz":
        if suffix not in SCAN_SUFFIXES:
            raise fail(path, f"unsupported scan format {suffix!r}; use one of .npz, {', '.join(SCAN_SUFFIXES)}")
        return read_scan(path, bin_columns)
    arrays = load_npz(path, required=(), optional=NPZ_KEYS)
    key = next((name for name in NPZ_KEYS if name in arrays), None)
    if key is None:
        raise fail(path, f"no array named {' or '.join(NPZ_KEYS)}")
    return check_points(arrays[key], path, key, allow_empty=False)


def read_transforms(path: Path, count: int) -> np.ndarray:
    """Exactly ``count`` rigid (4, 4) float64 transforms from text (12 or 16 values a line) or ``.npy``."""
    transforms = read_poses(path)
    if len(transforms) != count:
        raise fail(path, f"holds {len(transforms)} transform(s), expected {count}")
    for number, transform in enumerate(transforms, start=1):
        problem = rigid_problem(transform)
        if problem:
            raise fail(path, f"transform {number} {problem}")
    return transforms


def write_flow(path: Path, prediction) -> None:
    """``.npy``: the full flow; ``.npz``: flow, residual, in_grid, ground0, ego1_from_ego0, ego_estimated. Atomic."""
    with atomic_path(path, make_parents=True) as tmp, open(tmp, "wb") as handle:
        if path.suffix == ".npy":
            np.save(handle, prediction.flow)
        else:
            np.savez(
                handle,
                flow=prediction.flow,
                residual=prediction.residual,
                in_grid=prediction.in_grid,
                ground0=prediction.ground0,
                ego1_from_ego0=prediction.ego1_from_ego0,
                ego_estimated=np.bool_(prediction.ego_estimated),
            )


def parse_args(argv):
    parser = argparse.ArgumentParser(prog="python -m fastflow3d.infer", description=__doc__.splitlines()[0])
    parser.add_argument("model", type=Path, help="export directory, .onnx, .pt2, .pt (older TorchScript) or .ckpt")
    parser.add_argument("scan0", type=Path, help="scan at t (.npz, .npy, .bin, .ply, .pcd)")
    parser.add_argument("scan1", type=Path, help="scan at t + dt")
    ego = parser.add_mutually_exclusive_group()
    ego.add_argument("--poses", type=Path, help="two world_from_ego poses (scan0, scan1)")
    ego.add_argument("--ego", type=Path, help="one ego1_from_ego0 transform")
    parser.add_argument("--out", type=Path, help="flow file, .npz or .npy (default outputs/infer/<scan0>_flow.npz)")
    pictures = parser.add_mutually_exclusive_group()
    pictures.add_argument("--bev", type=Path, help="BEV PNG (default: the output's name with .png)")
    pictures.add_argument("--no-bev", action="store_true", help="write no picture")
    parser.add_argument("--extent", type=float, default=40.0, help="half-width of the picture in metres")
    parser.add_argument("--rerun", type=Path, metavar="FILE.rrd", help="also a 3D recording (icpflow.viz_rerun)")
    parser.add_argument(
        "--bin-columns",
        type=int,
        choices=range(3, 17),
        metavar="N",
        help="float32 values per row of a .bin scan, x, y, z first (default: x, y, z, r, checked)",
    )
    parser.add_argument("--backend", choices=(*FORMATS, *LEGACY_FORMATS), help="format of an export directory")
    parser.add_argument("--device", default="cpu", help="torch device for .pt2, .pt and checkpoints")
    parser.add_argument(
        "--runtime", choices=("onnxruntime", "openvino"), help="CPU engine for the ONNX file (fastflow3d.runtime)"
    )
    parser.add_argument("--threads", type=int, help="inference threads of --runtime (default: the usable cores)")
    return parser.parse_args(argv)


def infer(args) -> tuple[Path, Path | None]:
    """Read, predict, write; returns the flow path and the picture path (or None)."""
    from fastflow3d.predictor import Predictor
    from icpflow.viz import plot_bev

    out = args.out or Path("outputs/infer") / f"{args.scan0.stem}_flow.npz"
    if out.suffix not in (".npz", ".npy"):
        raise ValueError(f"{out}: output must end in .npz or .npy")
    pc0, pc1 = read_raw_scan(args.scan0, args.bin_columns), read_raw_scan(args.scan1, args.bin_columns)
    ego = None
    if args.poses is not None:
        pose0, pose1 = read_transforms(args.poses, 2)
        ego = relative_transform(pose0, pose1)
    elif args.ego is not None:
        ego = read_transforms(args.ego, 1)[0]
    predictor = Predictor.load(
        args.model, backend=args.backend, device=args.device, runtime=args.runtime, threads=args.threads
    )
    prediction = predictor.predict(pc0, pc1, ego)
    if not prediction.in_grid.any():
        print(
            f"infer: warning: no point of {args.scan0} lies inside the model's grid (nor is it kept as non-ground): "
            "its flow is the ego motion only; are the scans in metres, in the sensor's frame?",
            file=sys.stderr,
        )
    write_flow(out, prediction)
    if args.rerun is not None:  # the 3D viewer: pc0, pc1, the flow, ground and in-grid masks
        from icpflow.viz_rerun import record_pair

        ground0 = prediction.ground0 if predictor.remove_ground else None
        scans = FramePair(pc0=pc0, pc1=pc1, ego1_from_ego0=prediction.ego1_from_ego0, ground0=ground0)
        record_pair(args.rerun, scans, {"fastflow3d": prediction.flow}, prediction.in_grid)
    bev = None
    if not args.no_bev:
        bev = args.bev or out.with_suffix(".png")
        pair = FramePair(
            pc0=pc0,
            pc1=pc1,
            ego1_from_ego0=prediction.ego1_from_ego0,
            ground0=prediction.ground0 if predictor.remove_ground else None,
            source=str(args.scan0),
        )
        source = "estimated" if prediction.ego_estimated else "given"
        plot_bev(
            pair,
            bev,
            predicted=prediction.flow,
            extent=args.extent,
            title=f"{args.scan0.name} -> {args.scan1.name}: FastFlow3D ({predictor.backend}), ego motion {source}",
        )
    return out, bev


def main(argv=None) -> int:
    """Command-line entry; returns the exit status (0 written, 2 error)."""
    quiet()
    args = parse_args(argv)
    try:
        out, bev = infer(args)
    except OSError as error:  # a write error names the file asked for (icpflow.atomic), with the fix
        print(f"infer: {os_error_line(error)}", file=sys.stderr)
        return 2
    except (ValueError, RuntimeError) as error:
        print(f"infer: {' '.join(str(error).split())}", file=sys.stderr)
        return 2
    rerun = f", 3D -> {args.rerun}" if args.rerun else ""
    print(f"infer: flow -> {out}" + (f", BEV -> {bev}" if bev else "") + rerun)
    return 0


if __name__ == "__main__":
    sys.exit(main())
