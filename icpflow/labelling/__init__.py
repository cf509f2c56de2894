"""The labelling stage: plan samples into shards, label them with the teacher, write shards resumably.

Its names are imported on first use (``EXPORTS``): ``label.py`` starts from ``icpflow.labelling.launch`` without the
labelling's libraries (``icpflow.core.launch``)."""

#: the package's names -> the module that defines them
EXPORTS = {"LabelError": "job", "LabelJob": "job", "plan_shards": "plan", "run_labelling": "run"}

__all__ = sorted(EXPORTS)


def __getattr__(name: str):
    if name not in EXPORTS:
        raise AttributeError(f"module 'icpflow.labelling' has no attribute {name!r}")
    import importlib

    return getattr(importlib.import_module(f"icpflow.labelling.{EXPORTS[name]}"), name)
