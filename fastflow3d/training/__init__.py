"""The student's training (``train.py``): the LightningModule (``student_module``), shard data (``data``,
``augment``), losses (``loss``), schedules (``schedules``), callbacks (``callbacks``), the trainer and fit
(``trainer``), the run folder's rules (``run_folder``) and the structured configs of ``train.py`` and ``export.py``
(``options``). Imports ``fastflow3d.network`` and ``fastflow3d.artifact``, never ``fastflow3d.inference``."""
