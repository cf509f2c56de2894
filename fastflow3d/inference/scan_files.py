"""The files of ``fastflow3d-infer`` (``fastflow3d.inference.cli``): scans and transforms read, flows written, and no
output written over an input."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from icpflow.core.atomic import atomic_path
from icpflow.core.frame_pair import check_points
from icpflow.datasets.file_formats import SCAN_SUFFIXES, fail, load_npz, read_poses, read_scan

NPZ_KEYS = ("points", "pc")


def read_raw_scan(path: Path, bin_columns: int | None = None) -> np.ndarray:
    """(N, 3) float32 points of one scan file (``fastflow3d.inference.cli``'s module docstring lists the formats;
    ``bin_columns``: float32 values per row of a ``.bin``, see ``icpflow.datasets.file_formats.read_bin``)."""
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
    """Exactly ``count`` rigid (4, 4) float64 transforms from text (12 or 16 values a line) or ``.npy``
    (``read_poses``, which checks each one rigid)."""
    transforms = read_poses(path)
    if len(transforms) != count:
        raise fail(path, f"holds {len(transforms)} transform(s), expected {count}")
    return transforms


def write_flow(path: Path, prediction) -> None:
    """``.npy``: the full flow; ``.npz``: flow, residual, in_grid, ground0, ego1_from_ego0, ego_estimated (and
    ``refined`` with ``--refine``). Atomic."""
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
                ego_assumed=np.bool_(prediction.ego_assumed),
                **({} if prediction.refined is None else {"refined": prediction.refined}),
            )


def refuse_input_as_output(output: Path | None, inputs) -> None:
    """ValueError (one line) where ``output`` is one of the ``inputs`` (paths or None; the same file by any name)."""
    if output is None:
        return
    for given in inputs:
        if given is not None and (output.resolve() == given.resolve()):
            raise ValueError(f"{output}: is an input of this run; writing there would destroy it (give another --out)")
