"""What labels a sample: the teacher, or any flow source a config names (a distillation round's student).

A labeller is built once per process from its spec (:func:`build_labeller`; the ``labeller`` group's block as a plain
dict: ``conf/labeller/``) and called per sample as ``labeller(dataset, index, pair, horizon, threads)``, returning the
sample's labels (``icpflow.teacher.long_horizon.SampleFlow``: full flow in the ego frame of t + horizon, confidence,
ego motion, cluster ids, ground masks). ``teacher`` is the ICP-Flow teacher of the job's config; any other spec
names its class by ``_target_`` (``fastflow3d.inference.labeller``: a student export with the refinement, or the
teacher and a student in agreement), built with the block's other fields, the thread count and the job's teacher
config. The labeller's identity (its spec and, for a checkpoint, the hash
of its files: :func:`identity`) enters the run's config, so the shards record which labeller made them and a rerun
with another one is refused as another config.
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import json
from pathlib import Path

from icpflow.core.files import regular_file

TEACHER = "teacher"
#: keys of a spec that say what it is, not how the labeller is built
SPEC_KEYS = ("name", "_target_")


def is_teacher(spec: dict | None) -> bool:
    """Whether ``spec`` (None: the default) is the ICP-Flow teacher."""
    return spec is None or spec.get("name", TEACHER) == TEACHER


def files_hash(path: Path) -> str:
    """sha256 (hex, 16 digits) of a checkpoint file, or of every file of an export folder (names and contents, in
    order)."""
    digest = hashlib.sha256()
    if not path.is_dir():
        regular_file(path)  # a FIFO would hang the hash, a device would never end it
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for file in files:
        digest.update(str(file.relative_to(path) if path.is_dir() else file.name).encode())
        with open(file, "rb") as handle:
            for block in iter(functools.partial(handle.read, 1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()[:16]


def identity(spec: dict | None) -> dict | None:
    """What identifies a labeller in a run's config: None for the teacher (its settings are the config's ``teacher``
    block), else the spec's set fields with its ``checkpoint`` made absolute and the checkpoint's ``sha256``
    (:func:`files_hash`). Raises ``ValueError`` (one line) for a spec without ``_target_`` or a missing checkpoint."""
    if is_teacher(spec):
        return None
    spec = {key: value for key, value in spec.items() if value is not None}  # the fields another labeller has
    if not spec.get("_target_"):
        raise ValueError(f"labeller {spec.get('name')!r}: no _target_ names the class that labels")
    if spec.get("checkpoint") is not None:
        path = Path(str(spec["checkpoint"])).expanduser().absolute()
        if not path.exists():
            raise ValueError(f"labeller {spec.get('name')!r}: checkpoint {path} does not exist")
        spec["checkpoint"], spec["sha256"] = str(path), files_hash(path)
    return spec


def build_labeller(spec: dict, threads: int, teacher):
    """The labeller of a non-teacher ``spec`` (:func:`identity`'s form): its ``_target_`` class built with the
    other fields, ``threads`` and the run's ``teacher`` config (an ``ICPFlowConfig``: a labeller that runs the
    teacher too takes it); one per process, spec, thread count and teacher (a student loads its network once)."""
    return _built(json.dumps(spec, sort_keys=True), int(threads), json.dumps(teacher.to_dict(), sort_keys=True))


@functools.lru_cache(maxsize=2)
def _built(text: str, threads: int, teacher: str):
    from icpflow.teacher.config import ICPFlowConfig

    spec = json.loads(text)
    module, _, name = spec["_target_"].rpartition(".")
    options = {key: value for key, value in spec.items() if key not in (*SPEC_KEYS, "sha256")}
    cls = getattr(importlib.import_module(module), name)
    return cls(**options, threads=threads, teacher=ICPFlowConfig.from_dict(json.loads(teacher), warn=False))
