"""label.py runs on the small synthetic world (32 beams, 2 deg azimuth, 6 frames: 5 samples in shards of 2, 2, 1),
in this process or as a subprocess, and the checks of their output."""

import json
import os
import re
import signal
import sys
import time
from pathlib import Path

import numpy as np
from hydra import compose, initialize_config_dir

from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.shards import ShardDataset, verify_shard

REPO = Path(__file__).resolve().parents[2]
SMALL = [
    "dataset.reader.beams=32",
    "dataset.reader.azimuth_resolution_deg=2.0",
    "dataset.reader.num_sequences=1",
    "dataset.reader.frames_per_sequence=6",
    "shard_size=2",
    "limit=5",
]
#: the reader of SMALL's world
READER = {"split": "train", "num_sequences": 1, "frames_per_sequence": 6, "beams": 32, "azimuth_resolution_deg": 2.0}
#: environment of a label.py subprocess that can import the datasets defined in the tests (tests/ on its path)
TESTS_ENV = {
    **os.environ,
    "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO / "tests"), os.environ.get("PYTHONPATH")])),
}
#: label.py's summary line
SUMMARY = re.compile(
    r"label: (\d+) samples labelled, (\d+) skipped \(already done\), (\d+) failed; "
    r"mean \d+\.\d\d s/sample per worker, \d+\.\d\d samples/s in \d+\.\d s -> (.+)"
)


def label_cfg(out_dir, *overrides):
    """The composed label.py config of the small world into ``out_dir``, one worker unless ``overrides`` say."""
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose("label", [*SMALL, f"out_dir={out_dir}", "workers=1", *overrides])


def label_script(out_dir, *overrides) -> list[str]:
    """The label.py command line of the small world into ``out_dir``."""
    return [sys.executable, str(REPO / "label.py"), *SMALL, f"out_dir={out_dir}", *overrides]


def read_samples(out_dir) -> list[dict]:
    """Every sample of the shards in ``out_dir``, in index order."""
    dataset = ShardDataset(out_dir)
    samples = [dataset[i] for i in range(len(dataset))]
    dataset.close()
    return samples


def assert_same(out_a, out_b) -> None:
    """The shards of two output folders hold the same samples, array for array."""
    a, b = read_samples(out_a), read_samples(out_b)
    assert [s["sample_id"] for s in a] == [s["sample_id"] for s in b]
    for x, y in zip(a, b, strict=True):
        assert set(x) == set(y)
        for key in x:
            np.testing.assert_array_equal(x[key], y[key], err_msg=key)


def all_valid(out_dir) -> int:
    """Samples listed by ``index.json``, after checking each listed shard and that no temporary file is left."""
    index = json.loads((Path(out_dir) / "index.json").read_text())
    for shard in index["shards"]:
        verify_shard(Path(out_dir) / shard["file"], index["config_hash"], len(shard["samples"]))
    assert not list(Path(out_dir).glob("shard_*.tmp-*"))
    return sum(len(shard["samples"]) for shard in index["shards"])


def default_sigint() -> None:
    """In a child before exec: Ctrl-C back to its default, so a test does not depend on how pytest was started
    (a shell starts background jobs with SIGINT ignored, and an ignored SIGINT stays ignored across exec)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def running_in_group(group: int) -> list[int]:
    """Processes of process group ``group`` that still run (zombies left to a non-reaping init do not count)."""
    running = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:  # it ended meanwhile
            continue
        if int(fields[2]) == group and fields[0] != "Z":
            running.append(int(stat.parent.name))
    return running


def none_left_within(group: int, seconds: float = 10) -> bool:
    """Whether every process of the process group ``group`` is gone within ``seconds``."""
    deadline = time.monotonic() + seconds
    while running_in_group(group):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.1)
    return True


#: the environment of a rerun after an interrupted :class:`SlowSynthetic` run: the same config, no waiting
RERUN_ENV = {**TESTS_ENV, "SLOW_SYNTHETIC_SECONDS": "0"}


class SlowSynthetic(SyntheticDataset):
    """The small synthetic world, 2 s per sample from sample 2 on (time to interrupt the run); as fast as the world
    where ``SLOW_SYNTHETIC_SECONDS=0`` (:data:`RERUN_ENV`: a rerun, which has nothing to interrupt)."""

    def pair(self, index, horizon=1):
        if index >= 2:
            time.sleep(float(os.environ.get("SLOW_SYNTHETIC_SECONDS", "2")))
        return super().pair(index, horizon)
