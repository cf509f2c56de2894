"""What the benchmark scripts share: the checkout's paths and shipped samples, the configs composed as the entry
scripts compose them, the real scan pairs, timing and memory, and command-line overrides.

Scans are float32 ``(N, 3)`` arrays in their sensor's own frame (KITTI's velodyne frame, the AV2 ego frame).
"""

from __future__ import annotations

import argparse
import ast
import platform
import time
from pathlib import Path

import numpy as np

from icpflow.core.hardware import host_line
from icpflow.core.threads import cpu_fields

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"
#: the shipped samples (a sibling of the checkout)
DATA = ROOT.parent / "shared" / "data"
#: KITTI odometry sequence 01, frames 0-2: exact poses and SemanticKITTI labels
SEQ01 = DATA / "kitti_odometry_seq01" / "kitti_odom_seq01_frames000-002_with_gt_poses.npz"
#: SemanticKITTI learning map: road, parking, sidewalk, other-ground, terrain
GROUND_CLASSES = (9, 10, 11, 12, 17)


def compose(config: str, overrides: list[str]):
    """``conf/<config>.yaml`` (label, eval, train, export) with Hydra ``overrides``, as the entry script composes it:
    the schemas the configs extend are registered first."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    if config in ("train", "export"):
        from fastflow3d.training.options import register
    elif config == "label":
        from icpflow.labelling.options import register
    else:
        from icpflow.evaluation.options import register
    register()
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return hydra_compose(config, list(overrides))


def open_split(overrides: list[str]):
    """(dataset, eval config) of ``eval.py <overrides>``."""
    from icpflow.datasets.from_config import open_dataset

    cfg = compose("eval", overrides)
    return open_dataset(cfg, 1), cfg


def read_scan_pair(name: str, points: int = 0) -> tuple[np.ndarray, np.ndarray] | None:
    """(pc0, pc1) of a shipped pair: ``kitti`` (HDL-64E scans 000000, 000001, ~124k points each), ``av2`` (the
    Argoverse 2 pair, ~99k points each); None where ../shared/data lacks it. ``uniform``: ``points`` uniform random
    points each over x, y in [-32, 32) m and z in [-1, 3) m."""
    if name == "kitti":
        files = sorted((DATA / "kitti_hdl64_scans").glob("*.bin"))[:2]
        if len(files) < 2:
            return None
        return tuple(np.fromfile(f, dtype=np.float32).reshape(-1, 4)[:, :3].copy() for f in files)
    if name == "av2":
        import pandas as pd

        sweeps = sorted((DATA / "av2" / "sensor" / "val").glob("*/sensors/lidar/*.feather"))[:2]
        if len(sweeps) < 2:
            return None
        return tuple(pd.read_feather(s, columns=["x", "y", "z"]).to_numpy().astype(np.float32) for s in sweeps)
    rng = np.random.default_rng(0)
    return tuple((rng.random((points, 3)) * [64.0, 64.0, 4.0] - [32.0, 32.0, 1.0]).astype(np.float32) for _ in "01")


def timed(calls: dict, runs: int, warmup: int) -> dict[str, list[float]]:
    """Wall-clock seconds of ``runs`` calls of each function after ``warmup`` calls, taking turns within a run (so
    that a change of load on a shared machine hits all alike)."""
    for fn in calls.values():
        for _ in range(warmup):
            fn()
    times = {name: [] for name in calls}
    for _ in range(runs):
        for name, fn in calls.items():
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)
    return times


def rss_mb() -> float:
    """Current resident set size of this process (MB)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def cpu_name(cpuinfo: str | None = None) -> str:
    """The CPU as a benchmark's table names it: its model name, and on Linux its family, model, widest vector
    instructions, the instruction sets reduced precisions need and the switches in effect that hold engines below them
    (``icpflow.core.hardware.host_line``; ``cpuinfo``: the text of ``/proc/cpuinfo``, read when None). VMs here report
    "AMD EPYC" on hosts two times apart in speed (the int8 network alone on a KITTI pair: 57.9 ms in issue 44's eleventh
    session, 30.7 ms on a family 26 host in its twelfth), so a figure is compared with another only on the same family
    and model."""
    fields = cpu_fields(cpuinfo)
    name = fields.get("model name") or platform.processor() or "unknown CPU"
    if "cpu family" not in fields:
        return name
    flags = set(fields.get("flags", "").split())
    labels = (("avx512_vnni", "AVX-512 VNNI"), ("avx512f", "AVX-512"), ("avx2", "AVX2"), ("", "no AVX2"))
    widest = next(label for flag, label in labels if not flag or flag in flags)
    return f"{name} (family {fields['cpu family']} model {fields.get('model', '?')}, {widest}; {host_line(cpuinfo)})"


def split_overrides(text: str) -> list[str]:
    """Hydra overrides from ``a=1,b=[1,2],c=x``: split at the commas outside brackets."""
    items, depth, current = [], 0, ""
    for char in text:
        depth += (char in "[{(") - (char in "]})")
        if char == "," and depth == 0:
            items.append(current)
            current = ""
        else:
            current += char
    return [item for item in [*items, current] if item]


def literal_overrides(items: list[str], parser: argparse.ArgumentParser, flag: str) -> dict:
    """``ICPFlowConfig`` fields from ``FIELD=VALUE`` items, values parsed as Python literals (a bare word is a string:
    ``icp.dof=yaw``); an item without ``=`` is the parser's error."""
    fields = {}
    for item in items:
        if "=" not in item:
            parser.error(f"{flag} {item!r}: expected FIELD=VALUE")
        key, value = item.split("=", 1)
        try:
            fields[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            fields[key] = value
    return fields
