"""The stream mode of ``fastflow3d-infer`` (``fastflow3d.inference.cli``): which scans make the stream, and its
output folder, claimed before any work through its manifest (``stream.json``: the scans, the model and the options
of the run that wrote it; a rerun of the same stream replaces its own outputs, anything else is refused)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from icpflow.core.atomic import write_text_atomic
from icpflow.core.files import read_text
from icpflow.datasets.file_formats import SCAN_SUFFIXES, list_scans

#: a stream's manifest in its output folder (``MANIFEST_VERSION``: its layout)
MANIFEST, MANIFEST_VERSION = "stream.json", 1


def stream_files(where: Path) -> list[Path]:
    """The scans of a stream (``icpflow.datasets.file_formats.list_scans``: a folder or a glob, natural order, one scan
    per
    name stem)."""
    suffixes = (".npz", *SCAN_SUFFIXES)
    if not where.is_dir() and not any(char in str(where) for char in "*?["):
        raise ValueError(f"{where}: give two scans (a pair), or a folder or glob of scans (a stream)")
    files = list_scans(where, suffixes)
    if len(files) < 2:
        raise ValueError(f"{where}: a stream needs at least two scans ({', '.join(suffixes)}), found {len(files)}")
    return files


def stream_manifest(args, files: list[Path], precision: str) -> dict:
    """What identifies a stream's run (``MANIFEST``): its scans, model and the options that change its flows, with
    the ``precision`` its network runs in (what ``--precision auto`` chose)."""
    options = {name: getattr(args, name) for name in ("backend", "bin_columns", "refine", "sensor_height")}
    if precision != "f32":  # int8 / bf16 flows differ a little; f32 runs keep older manifests
        options["precision"] = precision
    return {
        "version": MANIFEST_VERSION,
        "model": str(args.model.resolve()),
        "scans": [str(path.resolve()) for path in files],
        "options": {
            name: value if isinstance(value, (int, float, str, type(None))) else str(value)
            for name, value in options.items()
        },
    }


def claim_output_folder(out: Path, manifest: dict, files: list[Path]) -> None:
    """Make ``out`` this stream's before any work: refused (ValueError, one line) where it holds an input scan, or
    anything but the outputs of this very stream (the same manifest: a rerun, said on stderr, replaces them; each is
    one of the names it writes, :func:`stream_outputs`, and a regular file, all checked before any is removed); then
    its manifest, marked incomplete until the run ends (:func:`write_manifest`)."""
    resolved = out.resolve()
    for path in files:
        if path.resolve().parent == resolved:
            raise ValueError(
                f"{out}: holds the input scans ({path.name}); the flows would replace them (give another --out)"
            )
    if out.exists() and not out.is_dir():
        raise ValueError(f"{out}: --out of a stream is a folder, and this is a file")
    present = sorted(out.iterdir()) if out.is_dir() else []
    if present:
        earlier = read_manifest(out / MANIFEST)
        if earlier is None or {k: earlier.get(k) for k in manifest} != manifest:
            what = "another stream's flows" if earlier is not None else f"{len(present)} file(s) of no stream of ours"
            if earlier is not None and all(earlier.get(k) == manifest[k] for k in ("model", "scans")):
                before, now = _options(earlier), _options(manifest)
                changed = ", ".join(
                    f"{k} {before.get(k)}, now {now.get(k)}" for k in now | before if before.get(k) != now.get(k)
                )
                what = f"this stream's flows made with other options ({changed})"
            raise ValueError(f"{out}: holds {what}; give an empty or new --out (outputs are never mixed)")
        own = stream_outputs(manifest) | {MANIFEST}
        for path in present:  # every entry checked before any is removed
            if path.name not in own:
                raise ValueError(f"{out}: holds {path.name}, not an output of this stream; give an empty or new --out")
            if path.is_symlink() or not path.is_file():
                raise ValueError(f"{out}: {path.name} is not a regular file; give an empty or new --out")
        print(
            f"infer: {out}: a rerun of the same stream; its {len(present) - 1} earlier output(s) are replaced",
            file=sys.stderr,
        )
        for path in present:
            if path.name != MANIFEST:
                path.unlink()
    write_manifest(out, manifest, [], complete=False)


def write_manifest(out: Path, manifest: dict, outputs: list[str], complete: bool, failed: list[dict] = ()) -> None:
    """``out``'s manifest: the run's identity, the flow files it holds (``outputs``, in order), whether the run
    ended (``complete``) and the pairs that could not be computed (``failed``: each ``{"scans": [scan0, scan1],
    "reason": ...}``, scan0 None where the scan had no pair); atomically."""
    document = {**manifest, "complete": complete, "outputs": outputs, "failed": list(failed)}
    write_text_atomic(out / MANIFEST, json.dumps(document, indent=1), make_parents=True)


def output_name(scan) -> str:
    """The flow file of the pair that starts at ``scan``: ``<its stem>.npz``."""
    return f"{Path(scan).stem}.npz"


def stream_outputs(manifest: dict) -> set[str]:
    """Every file name the stream of ``manifest`` may write into its folder, by name: one flow per scan but the last
    (``output_name``); a rerun removes these, and only these."""
    return {output_name(scan) for scan in manifest["scans"][:-1]}


def _options(manifest: dict) -> dict:
    """A manifest's options, its precision named where it leaves it out (float32: ``stream_manifest``)."""
    options = manifest.get("options")
    return {"precision": "f32", **(options if isinstance(options, dict) else {})}


def read_manifest(path: Path) -> dict | None:
    """A stream's manifest, or None where there is none or it is not one of ours."""
    try:
        document = json.loads(read_text(path))
    except (OSError, ValueError):
        return None
    return document if isinstance(document, dict) and document.get("version") == MANIFEST_VERSION else None
