"""The labelling stage: plan samples into shards, label them with the teacher, write shards resumably."""

from icpflow.labelling.job import LabelError, LabelJob
from icpflow.labelling.plan import plan_shards
from icpflow.labelling.run import run_labelling

__all__ = ["LabelError", "LabelJob", "plan_shards", "run_labelling"]
