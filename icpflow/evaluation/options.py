"""``eval.py``'s structured config (``conf/eval.yaml`` extends it): every option typed, with its rule
(``icpflow.core.settings``); as ``icpflow.labelling.options`` is ``label.py``'s. What a schema cannot say (a method's
checkpoint, a horizon the reader can give) is checked where it is used.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from omegaconf import MISSING

from icpflow.core.settings import setting, store
from icpflow.labelling.options import DatasetOptions, TeacherOverrides
from icpflow.viz.recording import VIEWERS


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
    viewer: str | None = setting(None, choices=(*VIEWERS, None))  # a 3D recording (icpflow.viz.recording)
    viewer_pairs: int = setting(10, "count")
    out_dir: str = MISSING
    hydra_dir: str = MISSING  # each launch's config and log (conf/hydra/default.yaml); unset: outputs/hydra/<script>


def register() -> None:
    """Store ``eval_schema`` (``conf/eval.yaml``'s base) in Hydra's ConfigStore. Idempotent; ``eval.py`` calls it
    before Hydra composes, and so must a caller of Hydra's compose API."""
    store("eval_schema", EvalOptions)
