"""``label.py`` and ``icpflow-label`` as they start (``icpflow.core.launch``): the command is imported inside."""

from icpflow.core.launch import launched


def _command():
    from icpflow.labelling.cli import main

    return main


def main() -> None:
    """``icpflow.labelling.cli.main``, imported where a Ctrl-C is one line (``icpflow.core.launch.launched``)."""
    launched("label", _command)
