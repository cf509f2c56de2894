"""The student's training (``train.py``): the LightningModule (``student_module``), shard data (``data``,
``augment``), losses (``loss``), schedules (``schedules``), callbacks (``callbacks``), the trainer and fit
(``trainer``), the run folder's rules (``run_folder``), the structured configs of ``train.py`` and ``export.py``
(``options``) and their entry points (``cli``: ``fastflow3d-train``, ``fastflow3d-export``). Imports
``fastflow3d.network`` and ``fastflow3d.artifact``, never ``fastflow3d.inference``."""

from icpflow.core.deprecation import moved_attribute

#: the names of the last release's module ``fastflow3d.training`` (this package since 0.2) -> their module today;
#: answered with a DeprecationWarning until 0.3 (``icpflow.core.deprecation``). Not its function ``run_folder``: that
#: name is today's module ``fastflow3d.training.run_folder`` (the function:
#: ``fastflow3d.training.run_folder.run_folder``)
MOVED = {
    **dict.fromkeys(
        (
            "log",
            "check_data",
            "training_contract",
            "build_module",
            "check_length",
            "export_formats",
            "build_trainer",
            "accumulation",
            "settle_batch",
            "best_checkpoint",
            "export_best",
            "check_sizes",
            "fit",
        ),
        "fastflow3d.training.trainer",
    ),
    **dict.fromkeys(
        (
            "TrainError",
            "resolve_ckpt_path",
            "kept_checkpoint",
            "check_fresh_start",
            "RESUME_FREE_DATA",
            "check_resume_settings",
        ),
        "fastflow3d.training.run_folder",
    ),
}


def __getattr__(name: str):
    """A name of the last release's ``fastflow3d.training`` module (:data:`MOVED`), with a DeprecationWarning."""
    return moved_attribute(__name__, name, MOVED)
