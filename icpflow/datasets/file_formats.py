"""File reading shared by the readers: every failure becomes a one-line :class:`FramePairError` naming the file.

Scans come back as (N, 3) float32 metres; poses as (T, 4, 4) float64. Nothing here knows a dataset's frames.
"""

from __future__ import annotations

import re
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from icpflow.core.errors_and_signals import one_line
from icpflow.core.files import NotAFile, read_text, regular_file
from icpflow.core.frame_pair import MAX_ARRAY_VALUES, MAX_POINTS, FramePairError, check_points
from icpflow.core.geometry import rigid_problem
from icpflow.core.stops import raise_stop_behind

if TYPE_CHECKING:
    import pandas as pd

SCAN_SUFFIXES = (".bin", ".npy", ".ply", ".pcd")


def natural_key(path: Path) -> list:
    """Sort key that orders ``2.bin`` before ``10.bin`` (and, for paths of several folders, folder by folder)."""
    return [[int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)] for name in path.parts]


def list_scans(where: Path, suffixes=SCAN_SUFFIXES, one_format: bool = False) -> list[Path]:
    """The scan files of a sequence, for every entry point that reads one (``dataset=sequence``, a stream of
    ``fastflow3d-infer``): the regular files of the folder ``where`` whose suffix is one of ``suffixes``, or the
    files a glob (``*``, ``?``, ``[``) matches, in natural order (``2.bin`` before ``10.bin``). Two scans of one
    name stem (``1.bin`` and ``1.npy``, or one name in two folders of a glob) are refused in one line: their outputs
    and sample ids would collide. ``one_format``: scans of several suffixes are refused too."""
    import glob

    wanted = {suffix.lower() for suffix in suffixes}
    if where.is_dir():
        found = [path for path in where.iterdir() if path.suffix.lower() in wanted and path.is_file()]
    elif any(char in str(where) for char in "*?["):
        found = [Path(name) for name in glob.glob(str(where)) if Path(name).is_file()]
    else:
        raise fail(where, "not a folder of scans, nor a glob")
    scans = sorted(found, key=natural_key)
    formats = sorted({path.suffix.lower() for path in scans})
    if one_format and len(formats) > 1:
        raise fail(where, f"need scans of one format, found {', '.join(formats)}")
    first: dict[str, Path] = {}
    for path in scans:
        other = first.setdefault(path.stem, path)
        if other is not path:
            raise fail(
                where,
                f"two scans named {path.stem!r} ({other} and {path}): rename one (outputs and sample ids are named "
                "by the stem)",
            )
    return scans


def fail(path, message: str) -> FramePairError:
    """A one-line error naming ``path``."""
    return FramePairError(f"{path}: {one_line(message)}")


def check_file(path: Path) -> int:
    """The size of the regular file ``path``; a one-line :class:`FramePairError` where it is missing or is something
    else (a FIFO, a device, a folder: ``icpflow.core.files``), before it is opened."""
    try:
        return regular_file(path).st_size
    except FileNotFoundError:
        raise fail(path, "file not found") from None
    except NotAFile as error:
        raise FramePairError(str(error)) from None


def load_npz(path: Path, required: tuple[str, ...], optional: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """The ``required`` and present ``optional`` arrays of an ``.npz`` (all of them if ``optional`` is None).

    Other keys are not read (they may hold pickled objects, which are never loaded). Missing ``required`` keys
    or a damaged file raise.
    """
    check_file(path)
    try:
        with open(path, "rb") as handle:
            start = handle.read(4)
    except FileNotFoundError:
        raise fail(path, "file not found") from None
    if start not in (b"PK\x03\x04", b"PK\x05\x06"):  # a zip archive's first record, or an empty archive
        raise fail(path, "not an .npz file (an .npz is a zip archive of .npy arrays)")
    try:
        with np.load(path, allow_pickle=False) as data:
            wanted = data.files if optional is None else [k for k in data.files if k in (*required, *optional)]
            for key in wanted:  # what each member claims, before it is inflated (a zip of zeros is tiny)
                shape, itemsize = _npz_member_shape(data.zip, key)
                check_claim(path, key, shape, data.zip.getinfo(f"{key}.npy").file_size, itemsize)
            arrays = {key: data[key] for key in wanted}
    except FileNotFoundError:
        raise fail(path, "file not found") from None
    except (zipfile.BadZipFile, EOFError, OSError, ValueError, KeyError, MemoryError, OverflowError) as error:
        if isinstance(error, FramePairError):
            raise
        raise fail(path, f"cannot read .npz (truncated or damaged?): {type(error).__name__}: {error}") from None
    missing = [key for key in required if key not in arrays]
    if missing:
        raise fail(path, f"missing key(s) {', '.join(missing)}; has {', '.join(sorted(arrays)) or 'none'}")
    return arrays


def check_claim(path: Path, name: str, shape: tuple, available: int | None = None, itemsize: int = 1) -> None:
    """Refuse (one line naming ``path`` and ``name``) an array whose ``shape`` claims more than ``MAX_POINTS`` rows
    or ``MAX_ARRAY_VALUES`` values, or, where ``available`` bytes are known, more bytes (``itemsize`` per value)
    than that: checked by every reader before it allocates."""
    values = int(np.prod(shape, dtype=object)) if len(shape) else 1
    if len(shape) and shape[0] > MAX_POINTS:  # rows are points (scans, per-point arrays)
        raise fail(
            path, f"{name} claims {shape[0]} rows (points), over the cap of {MAX_POINTS} (icpflow.core.frame_pair)"
        )
    if values > MAX_ARRAY_VALUES:
        cap = f"over the cap of {MAX_ARRAY_VALUES} values (icpflow.core.frame_pair.MAX_POINTS)"
        raise fail(path, f"{name} claims shape {tuple(shape)}, {cap}")
    if available is not None and values * itemsize > available:
        raise fail(path, f"{name} claims shape {tuple(shape)}, more than the file's {available} bytes (truncated?)")


def _npy_header(handle) -> tuple[tuple, np.dtype]:
    """(shape, dtype) of the ``.npy`` header at ``handle``'s position (left just after it)."""
    version = np.lib.format.read_magic(handle)
    read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
    shape, _, dtype = read(handle)
    return tuple(shape), dtype


def _npz_member_shape(archive: zipfile.ZipFile, key: str) -> tuple[tuple, int]:
    """(shape, bytes per value) an ``.npz`` member's ``.npy`` header declares (nothing inflated but the header)."""
    with archive.open(f"{key}.npy") as member:
        shape, dtype = _npy_header(member)
    return shape, dtype.itemsize


def load_npy(path: Path) -> np.ndarray:
    """The array of a ``.npy`` file; never unpickles (an object array is refused). A missing, foreign (no NumPy
    header), truncated or damaged file raises one line naming it."""
    check_file(path)
    try:
        with open(path, "rb") as handle:
            start = handle.read(6)
    except FileNotFoundError:
        raise fail(path, "file not found") from None
    if start != b"\x93NUMPY":
        raise fail(path, "not a .npy file (no NumPy header)" if start else "empty file")
    try:
        with open(path, "rb") as handle:
            shape, dtype = _npy_header(handle)
            header = handle.tell()
        if dtype.hasobject:
            raise ValueError("Object arrays cannot be loaded when allow_pickle=False")
        check_claim(path, "the array", shape, path.stat().st_size - header, dtype.itemsize)
        return np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as error:
        if isinstance(error, FramePairError):
            raise
        raise fail(path, f"cannot read .npy (truncated or damaged?): {error}") from None


def read_feather(path: Path, columns: tuple[str, ...], optional: tuple[str, ...] = ()) -> pd.DataFrame:
    """The given ``columns`` of a feather file (Arrow IPC) and those of ``optional`` it has; a missing file or column
    or a damaged file raises. The rows its record batches claim are bounded (:func:`check_claim`) before pyarrow
    decompresses any of them, and only these columns are read (pandas is imported here: a third of a second that
    every process reading other formats is spared)."""
    import pandas as pd

    check_file(path)
    try:
        rows, names = _feather_rows(path)
        check_claim(path, "its record batches", (rows, max(1, len(columns))))
        missing = [column for column in columns if column not in names]
        if missing:
            raise fail(path, f"missing column(s) {', '.join(missing)}; has {', '.join(map(str, names))}")
        return pd.read_feather(path, columns=[*columns, *(column for column in optional if column in names)])
    except FramePairError:
        raise
    except FileNotFoundError:
        raise fail(path, "file not found") from None
    except Exception as error:  # pyarrow raises several unrelated types for damaged files
        raise_stop_behind(error)
        raise fail(path, f"cannot read feather (truncated or damaged?): {type(error).__name__}: {error}") from None


def _feather_rows(path: Path) -> tuple[int, list[str]]:
    """(rows of every record batch, column names) of an Arrow IPC file, read from its messages' metadata: each
    batch's compressed body is read (no more than the file holds), none is decompressed."""
    import struct

    import pyarrow as pa

    def field(buffer: bytes, table: int, index: int) -> int | None:  # a flatbuffer table's field position
        vtable = table - struct.unpack_from("<i", buffer, table)[0]
        if 4 + 2 * index >= struct.unpack_from("<H", buffer, vtable)[0]:
            return None
        offset = struct.unpack_from("<H", buffer, vtable + 4 + 2 * index)[0]
        return table + offset if offset else None

    with pa.OSFile(str(path)) as handle:
        names = pa.ipc.open_file(handle).schema.names
        handle.seek(8)  # the file's magic, then the stream of messages
        reader, rows = pa.ipc.MessageReader.open_stream(handle), 0
        while (message := _next_message(reader)) is not None:
            if message.type != "record batch":
                continue
            meta = message.metadata.to_pybytes()  # a Message table: its header (field 2) is the RecordBatch
            root = struct.unpack_from("<I", meta, 0)[0]
            header = field(meta, root, 2)
            batch = header + struct.unpack_from("<I", meta, header)[0]
            length = field(meta, batch, 0)
            rows += struct.unpack_from("<q", meta, length)[0] if length is not None else 0
    return rows, names


def _next_message(reader):
    """The next message of an Arrow IPC stream, None at its end."""
    try:
        return reader.read_next_message()
    except StopIteration:
        return None


#: KITTI's ``.bin`` layout: float32 rows of x, y, z, reflectance
BIN_COLUMNS = 4
#: coordinates beyond this many metres in a ``.bin`` mean another layout, dtype or unit
BIN_MAX_RANGE = 10_000.0
#: a scan's median range (m) beyond which its coordinates are not metres (a LiDAR's median return is 5-40 m)
BIN_PLAUSIBLE_MEDIAN = 500.0


def read_bin(path: Path, columns: int | None = None) -> np.ndarray:
    """Raw ``.bin``: float32 rows of ``columns`` values, x, y, z first -> (N, 3) float32.

    ``columns`` None: the KITTI layout (x, y, z, reflectance). Whatever the layout, the values are checked for
    plausibility: non-finite or huge coordinates (beyond ``BIN_MAX_RANGE`` m: float64 values or another layout read
    as float32 rows) and, in the default layout, negative reflectance are an error; without ``columns`` it asks for
    the column count (``bin_columns`` / ``--bin-columns``). Coordinates that are metres a thousand (or a hundred)
    times over (a median range of kilometres) are said to look like millimetres (or centimetres): convert them.
    """
    size = check_file(path)
    ask = "" if columns else "; if its layout is not x, y, z, r give its column count (bin_columns=N, --bin-columns N)"
    width = columns or BIN_COLUMNS
    if size % (4 * width):
        raise fail(path, f"size {size} bytes is not a whole number of {width}-float32 rows (truncated?){ask}")
    check_claim(path, "the rows", (size // (4 * width), width))
    values = np.fromfile(path, dtype=np.float32).reshape(-1, width)
    if len(values):
        xyz = values[:, :3]
        with np.errstate(invalid="ignore", over="ignore"):
            finite = bool(np.isfinite(xyz).all())  # the rows' test (a short-axis reduction) only where one fails
            kept = xyz if finite else xyz[np.isfinite(xyz).all(axis=1)]
            # squared ranges in float32 (a plausibility test needs no more; a coordinate past 1e19 m overflows to
            # inf, beyond any bound): 4x quicker than the float64 norms of a copy
            squared = np.einsum("ij,ij->i", kept, kept)
        farthest = float(np.sqrt(squared.max())) if len(squared) else 0.0
        median = float(np.sqrt(np.median(squared))) if farthest > BIN_PLAUSIBLE_MEDIAN else 0.0  # only then can it be
        if median > BIN_PLAUSIBLE_MEDIAN:  # the unit whose median range is nearest a LiDAR's (10 m)
            unit, factor = min(
                (("millimetres", 1000.0), ("centimetres", 100.0)), key=lambda u: abs(np.log10(median / u[1] / 10))
            )
            if median / factor <= BIN_PLAUSIBLE_MEDIAN and farthest / factor <= BIN_MAX_RANGE:
                raise fail(
                    path,
                    f"its median range is {median:.0f} m: the coordinates look like {unit} (median "
                    f"{median / factor:.1f} m in metres); convert the scan to metres",
                )
        reflectance = columns is None and bool((values[:, 3] < 0).any())
        # without a layout any NaN says "another layout"; with one, a few NaN rows are check_points' to count
        if (columns is None and not finite) or farthest > BIN_MAX_RANGE or reflectance:
            layout = "x, y, z, r" if columns is None else f"{width} values, x, y, z first"
            raise fail(
                path,
                f"values are implausible for float32 rows of {layout} (NaN or Inf, beyond {BIN_MAX_RANGE:.0f} m"
                f"{', or negative reflectance' if columns is None else ''}): float64 values, another layout or "
                f"another unit?{ask}",
            )
    return check_points(values, path, "scan", allow_empty=False)


def read_scan(path: Path, bin_columns: int | None = None) -> np.ndarray:
    """One scan from ``.bin`` (float32 rows, :func:`read_bin`), ``.npy`` (N, >= 3), ``.ply`` or ``.pcd`` (open3d);
    what a file claims is bounded (:func:`check_claim`), and a reader that still runs out of memory or range is one
    line naming the file."""
    try:
        return _read_scan(path, bin_columns)
    except (MemoryError, OverflowError) as error:
        raise fail(path, f"too large to read ({type(error).__name__}: {error})") from None


def _read_scan(path: Path, bin_columns: int | None) -> np.ndarray:
    suffix = path.suffix.lower()
    if suffix == ".bin":
        return read_bin(path, bin_columns)
    if suffix == ".npy":
        return check_points(load_npy(path), path, "scan", allow_empty=False)
    if suffix in (".ply", ".pcd"):
        check_file(path)
        declared = (check_ply_complete if suffix == ".ply" else check_pcd_complete)(path)
        from icpflow.core.open3d_loader import load_open3d

        o3d = load_open3d()  # imported here: only these two formats need it
        cloud = o3d.io.read_point_cloud(str(path), format="auto")
        points = np.asarray(cloud.points)
        if len(points) == 0:
            raise fail(path, "no points read (empty, truncated or not a point cloud)")
        if declared is not None and len(points) != declared:  # open3d pads or cuts a file it failed to read
            raise fail(path, f"open3d read {len(points)} points of the {declared} its header declares (damaged?)")
        return check_points(points, path, "scan", allow_empty=False)
    raise fail(path, f"unsupported scan format {suffix!r}; use one of {', '.join(SCAN_SUFFIXES)}")


PLY_SIZES = {
    "char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
    "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8,
}  # fmt: skip


def check_ply_complete(path: Path) -> int:
    """The vertex count a PLY file's header declares; raise if the file holds fewer vertex bytes or lines than that,
    if it claims more than ``MAX_POINTS``, or if its vertices hold list or unknown properties (their sizes vary: a
    280-byte file could claim gigabytes).

    open3d reads a truncated PLY without an error (it pads the missing vertices), so the header is checked first.
    """
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise fail(path, "not a PLY file (no 'ply' ... 'end_header' header)")
    header = data[:end].decode("ascii", errors="replace").splitlines()
    body = data[data.index(b"\n", end) + 1 :]
    fmt = next((line.split()[1] for line in header if line.startswith("format")), "")
    elements = [line.split() for line in header if line.startswith(("element", "property"))]
    if not elements or elements[0][:2] != ["element", "vertex"] or not elements[0][2:3] or not elements[0][2].isdigit():
        raise fail(path, "PLY header has no leading 'element vertex N'")
    count = int(elements[0][2])
    check_claim(path, "the PLY header", (count, 3))
    properties = []
    for entry in elements[1:]:
        if entry[0] == "element":
            break
        properties.append(entry)
    if fmt == "ascii":
        available = len([line for line in body.splitlines() if line.strip()])
        needed = count
    elif any(entry[1] == "list" or entry[1] not in PLY_SIZES for entry in properties):
        kinds = sorted({entry[1] for entry in properties if entry[1] == "list" or entry[1] not in PLY_SIZES})
        raise fail(path, f"its vertices have {', '.join(kinds)} properties: not a point cloud of fixed-size rows")
    else:
        available, needed = len(body), count * sum(PLY_SIZES[entry[1]] for entry in properties)
    if available < needed:
        raise fail(path, f"truncated: header declares {count} vertices, the file holds less")
    return count


def check_pcd_complete(path: Path) -> int | None:
    """The point count a PCD file's header declares (None for ``binary_compressed``); raise if the file holds fewer
    points than that (``POINTS``, else ``WIDTH x HEIGHT``) or claims more than ``MAX_POINTS``.

    open3d reads a truncated PCD without an error (the points present), as it does a PLY (:func:`check_ply_complete`).
    ``DATA binary_compressed`` is left to open3d (its sizes are in the compressed block)."""
    data = path.read_bytes()
    at = data.find(b"\nDATA ")
    if not data.lstrip().startswith((b"#", b"VERSION", b"FIELDS")) or at < 0:
        raise fail(path, "not a PCD file (no header ending in a 'DATA' line)")
    line_end = data.find(b"\n", at + 1)
    header = data[: at + 1].decode("ascii", errors="replace").splitlines()
    kind = data[at + 6 : line_end if line_end >= 0 else len(data)].decode("ascii", errors="replace").strip()
    body = data[line_end + 1 :] if line_end >= 0 else b""
    fields = {line.split()[0]: line.split()[1:] for line in header if line.strip() and not line.startswith("#")}
    try:
        if "POINTS" in fields:
            count = int(fields["POINTS"][0])
        else:
            count = int(fields["WIDTH"][0]) * int(fields["HEIGHT"][0])
        sizes = [int(v) for v in fields["SIZE"]]
        counts = [int(v) for v in fields.get("COUNT", ["1"] * len(sizes))]
    except (KeyError, IndexError, ValueError):
        raise fail(path, "PCD header lacks POINTS (or WIDTH and HEIGHT) and SIZE") from None
    check_claim(path, "the PCD header", (count, 3))
    if kind == "ascii":
        available, needed = len([line for line in body.splitlines() if line.strip()]), count
    elif kind == "binary":
        available, needed = len(body), count * sum(size * n for size, n in zip(sizes, counts))
    else:
        return None
    if available < needed:
        raise fail(path, f"truncated: header declares {count} points, the file holds less")
    return count


def read_pose_lines(path: Path) -> np.ndarray:
    """Poses from text, one per line: 12 values (a row-major 3 x 4 matrix, KITTI) or 16 (4 x 4) -> (T, 4, 4)."""
    check_file(path)
    try:
        lines = [line.split() for line in read_text(path).splitlines() if line.strip()]
    except NotAFile as error:
        raise FramePairError(str(error)) from None
    poses = np.tile(np.eye(4), (len(lines), 1, 1))
    for number, values in enumerate(lines, start=1):
        if len(values) not in (12, 16):
            raise fail(path, f"line {number} has {len(values)} values, expected 12 (3 x 4) or 16 (4 x 4)")
        try:
            matrix = np.array(values, dtype=np.float64)
        except ValueError:
            raise fail(path, f"line {number} is not numeric") from None
        poses[number - 1, : len(values) // 4] = matrix.reshape(-1, 4)
    if len(poses) == 0:
        raise fail(path, "no poses")
    return poses


def read_poses(path: Path) -> np.ndarray:
    """(T, 4, 4) float64 transforms (e.g. world-from-sensor poses) from a text file (see :func:`read_pose_lines`)
    or a ``.npy`` of shape (T, 4, 4) or one (4, 4); each one checked rigid."""
    if path.suffix.lower() == ".npy":
        poses = load_npy(path)
        if poses.shape == (4, 4):
            poses = poses[None]
        if poses.ndim != 3 or poses.shape[1:] != (4, 4) or not np.issubdtype(poses.dtype, np.number):
            raise fail(path, f"poses must have shape (T, 4, 4), got {poses.dtype} {poses.shape}")
        poses = poses.astype(np.float64)
    else:
        try:
            poses = read_pose_lines(path)
        except UnicodeDecodeError:
            raise fail(path, "not a text file of poses (use .npy for binary)") from None
    for index, pose in enumerate(poses):
        problem = rigid_problem(pose)
        if problem:
            where = "" if path.suffix.lower() == ".npy" else f" (line {index + 1})"
            raise fail(path, f"transform {index + 1}{where} {problem}")
    return poses
