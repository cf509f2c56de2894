"""The Hydra configs of the entry points (``label.yaml``, ``train.yaml``, ``eval.yaml``, ``export.yaml`` and their
groups). A package only so that a wheel carries them: setup.py installs this folder as ``icpflow_conf``, which the
console scripts read as ``pkg://icpflow_conf`` when there is no checkout (``icpflow.core.entry_points.config_path``)."""
