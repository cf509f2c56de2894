"""``train.py``, ``export.py`` and their console scripts as they start (``icpflow.core.launch``): each command is
imported inside, where a Ctrl-C while torch and Lightning load is one line."""

from icpflow.core.launch import launched


def _train():
    from fastflow3d.training.cli import train_main

    return train_main


def _export():
    from fastflow3d.training.cli import export_main

    return export_main


def train_main() -> None:
    """``fastflow3d.training.cli.train_main`` (``train.py``, ``fastflow3d-train``)."""
    launched("train", _train)


def export_main() -> None:
    """``fastflow3d.training.cli.export_main`` (``export.py``, ``fastflow3d-export``)."""
    launched("export", _export)
