"""``label.py``'s structured config (``conf/label.yaml`` extends it) and the ``dataset`` group's
(``conf/dataset/*.yaml``, which ``eval.py`` shares): every option typed, with its rule (``icpflow.core.settings``).

Values come from the YAML files (the one place of defaults); a field here says what the option may hold. Hydra
refuses a value of the wrong type or an unknown key while composing; :func:`icpflow.core.settings.check_config`
checks the rules before any work. What a schema cannot say (the dataset's root exists, a horizon the reader can
give) is checked where it is used.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from omegaconf import MISSING

from icpflow.core.settings import setting, store
from icpflow.shards.schema import COMPRESSIONS
from icpflow.teacher.config import PRESETS, schema

#: the teacher's overrides (``icpflow.*`` and a dataset's ``teacher`` block): every field null = the preset's value
TeacherOverrides = schema()


@dataclass
class DatasetOptions:
    """``conf/dataset/<name>.yaml``: which reader, where its files are, and the teacher settings for it."""

    name: str = MISSING
    root: str | None = MISSING  # ??? = must be given (dataset.root=...); null = the reader reads no files
    eval_crop: float | None = setting(None, "positive")  # half-width (m) of the xy box metrics score
    preset: str = setting(MISSING, choices=tuple(PRESETS))  # the teacher's preset for this dataset
    reader: Any = MISSING  # the reader's _target_ and its arguments (checked by the reader when it is opened)
    teacher: TeacherOverrides = field(default_factory=TeacherOverrides)  # over the preset, as icpflow.* is


@dataclass
class RayOptions:
    address: str | None = None  # null = a local Ray with `workers` CPUs; auto = an existing cluster


@dataclass
class LabellerOptions:
    """``conf/labeller/<name>.yaml``: what labels the samples. ``teacher``: the ICP-Flow teacher; any other names a
    ``_target_`` class built with the block's other fields (``icpflow.labelling.labeller``), e.g. a student export
    with the refinement (``conf/labeller/student.yaml``)."""

    name: str = "teacher"
    _target_: str | None = None
    checkpoint: str | None = None
    refine: bool = True
    precision: str = setting("auto", choices=("auto", "f32", "bf16", "int8"))
    agree: float | None = setting(None, "positive")  # agreement's: m within which the teacher's flow is kept


@dataclass
class LabelOptions:
    """``label.py`` (``conf/label.yaml``)."""

    dataset: DatasetOptions = MISSING
    icpflow: TeacherOverrides = MISSING
    labeller: LabellerOptions = field(default_factory=LabellerOptions)
    split: str = MISSING
    workers: int | None = setting(None, "count")
    out_dir: str = MISSING
    shard_size: int = setting(32, "count")
    limit: int | None = setting(None, "count")
    horizon: int = setting(1, "count")
    tracker: bool = False
    overwrite: bool = False
    runner: str = setting("local", choices=("local", "ray"))
    ray: RayOptions = field(default_factory=RayOptions)
    shard_index: int = setting(0, "count_or_zero")
    num_shards: int = setting(1, "count")
    compression: str | None = setting("none", choices=(*COMPRESSIONS, None))
    hydra_dir: str = MISSING  # each launch's config and log (conf/hydra/default.yaml); unset: outputs/hydra/<script>


def register() -> None:
    """Store ``label_schema`` (``conf/label.yaml``'s base) in Hydra's ConfigStore. Idempotent; ``label.py`` calls it
    before Hydra composes, and so must a caller of Hydra's compose API."""
    store("label_schema", LabelOptions)
