"""``fastflow3d-infer``, ``eval.py`` and ``fastflow3d-eval`` as they start (``icpflow.core.launch``): each command is
imported inside, where a Ctrl-C while torch loads is one line."""

from icpflow.core.launch import launched


def _infer():
    from fastflow3d.inference.cli import main

    return main


def _eval():
    from fastflow3d.inference.eval_cli import main

    return main


def infer(argv=None) -> int:
    """``fastflow3d.inference.cli.main`` (``fastflow3d-infer``); returns its exit status. Given ``argv``, it is a call
    within a program that goes on, whose Ctrl-C is left as it was."""
    return launched("infer", _infer, argv, exits=argv is None)


def eval_main() -> None:
    """``fastflow3d.inference.eval_cli.main`` (``eval.py``, ``fastflow3d-eval``)."""
    launched("eval", _eval)
