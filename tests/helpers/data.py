"""The real samples shipped beside the checkout (``../shared/data``: the Argoverse 2 log, KITTI sequence 01 frames,
the bare KITTI HDL-64 scans, the KITTI sequence 00 pairs) and the one way a test skips where one is absent.

``needs_shared(...)`` marks a test (or, as ``pytestmark``, a module); ``require_shared(...)`` skips from inside a
fixture or a test body (where only some parameters or some fixtures' users read the sample). Both give the reason
``needs ../shared/data/<parts> (<what>), absent here``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import pytest

#: the checkout's root, from this file's own place (tests/helpers/data.py), wherever the test files sit
REPO = Path(__file__).resolve().parents[2]
#: the real samples, in the checkout's sibling folder
SHARED_DATA = REPO.parent / "shared" / "data"

Kind = Literal["dir", "file", "exists"]


def shared(*parts: str) -> Path:
    """``../shared/data/<parts...>`` (one part may hold slashes: ``shared("av2/sensor/val")``)."""
    return SHARED_DATA.joinpath(*parts)


def _present(path: Path, kind: Kind, glob: str | None) -> bool:
    if glob is not None:
        return any(path.glob(glob))
    return {"dir": path.is_dir, "file": path.is_file, "exists": path.exists}[kind]()


def _reason(parts: tuple[str, ...], what: str, glob: str | None) -> str:
    name = "/".join(parts) + (f"/{glob}" if glob else "")
    return f"needs ../shared/data/{name} ({what}), absent here"


def needs_shared(*parts: str, what: str, kind: Kind = "dir", glob: str | None = None) -> pytest.MarkDecorator:
    """A skip mark for tests that read ``shared(*parts)``: present where it is a folder (``kind="dir"``), a file
    (``"file"``) or either (``"exists"``); with ``glob``, where the folder holds at least one match of it."""
    return pytest.mark.skipif(not _present(shared(*parts), kind, glob), reason=_reason(parts, what, glob))


def require_shared(*parts: str, what: str, kind: Kind = "dir", glob: str | None = None) -> Path:
    """``shared(*parts)``, or skip the calling test (as ``needs_shared`` would) where it is absent."""
    path = shared(*parts)
    if not _present(path, kind, glob):
        pytest.skip(_reason(parts, what, glob))
    return path
