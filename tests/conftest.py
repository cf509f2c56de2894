"""Settings shared by every test."""

import pytest
import torch


@pytest.fixture(scope="session", autouse=True)
def one_torch_thread():
    """One torch thread: the test networks are tiny, and on a busy 2-core machine (CI) two threads fighting over
    the cores make them several times slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def reference(tmp_path_factory):
    """The small world labelled once per session by an uninterrupted single-worker run (helpers.labelling): 5 samples
    in shards of 2, 2, 1; the output every faulted, resumed or parallel run must reproduce."""
    from icpflow.labelling.cli import label

    from helpers.labelling import label_cfg

    out = tmp_path_factory.mktemp("reference") / "labels"
    assert label(label_cfg(out), progress=False) == 0
    return out
