"""The structured configs of ``label.py`` and ``eval.py`` (``conf/label.yaml`` and ``conf/eval.yaml`` extend them)
and of the ``dataset`` group they share: every option typed, with its rule (``icpflow.settings``).

Values come from the YAML files (the one place of defaults); a field here says what the option may hold. Hydra
refuses a value of the wrong type or an unknown key while composing; :func:`icpflow.settings.check_config` checks
the rules before any work. What a schema cannot say (the dataset's root exists, a horizon the reader can give, a
method's checkpoint) is checked where it is used.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from omegaconf import MISSING

from icpflow.settings import setting, store
from icpflow.shards.schema import COMPRESSIONS
from icpflow.teacher.config import PRESETS, schema
from icpflow.viz_rerun import VIEWERS

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


@dataclass
class EvalOptions:
    """``eval.py`` (``conf/eval.yaml``). ``method``, ``horizon`` and ``tracker`` take a value or a list
    (``icpflow.evaluation.methods`` reads them)."""

    dataset: DatasetOptions = MISSING
    icpflow: TeacherOverrides = MISSING
    split: str = MISSING
    method: Any = MISSING  # a method's name or a list of them
    checkpoint: str | None = None
    sensor_height: float | str | None = None  # metres, auto or null (fastflow3d.inference.predictor)
    precision: str = setting("auto", choices=("auto", "f32", "bf16", "int8"))  # the student's network (Predictor.load)
    shards: str | None = None
    horizon: Any = 1  # a gap, a list of gaps or first..last
    tracker: Any = False  # true, false or [false,true]
    limit: int | None = setting(None, "count")
    crop: float | None = setting(None, "positive")
    include_ground: bool = False
    relative_to: str = setting("residual", choices=("residual", "full"))
    weighting: str = setting("point_weighted", choices=("point_weighted", "per_pair"))
    bev: int = setting(1, "count_or_zero")
    bev_extent: float = setting(40.0, "positive")
    render: int = setting(0, "count_or_zero")
    render_size: list[int] = setting([1280, 720], "pixel_size")
    viewer: str | None = setting(None, choices=(*VIEWERS, None))  # a 3D recording (icpflow.viz_rerun)
    viewer_pairs: int = setting(10, "count")
    out_dir: str = MISSING
    hydra_dir: str = MISSING  # each launch's config and log (conf/hydra/default.yaml); unset: outputs/hydra/<script>


def register() -> None:
    """Store ``label_schema`` and ``eval_schema`` (the primary configs' bases) in Hydra's ConfigStore. Idempotent;
    ``label.py`` and ``eval.py`` call it before Hydra composes, and so must a caller of Hydra's compose API."""
    store("label_schema", LabelOptions)
    store("eval_schema", EvalOptions)
