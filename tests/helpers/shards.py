"""Shards written by hand in label.py's layout (``icpflow.shards``): samples from frame pairs, then the shard files
and their ``index.json``."""

from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from icpflow.shards.writer import write_index, write_shard
from icpflow.teacher.config import ICPFlowConfig

#: the teacher that "labelled" hand-made training shards (the synthetic dataset's: conf/dataset/synthetic.yaml)
TEACHER = ICPFlowConfig.preset("waymo", ground={"sensor_height": 1.9, "patchwork_z_offset": -1.9})


def pair_sample(pair, index: int, flow, confidence, cluster, with_gt: bool = True) -> dict:
    """The shard rows of frame pair ``pair`` as sample ``index``, with pseudo ``flow`` (N0, 3), ``confidence`` (N0,)
    and ``cluster`` (N0,), and the pair's ground truth when ``with_gt``."""
    sample = {
        "pc0": pair.pc0,
        "pc1": pair.pc1,
        "ground0": pair.ground0,
        "ground1": pair.ground1,
        "ego1_from_ego0": pair.ego1_from_ego0,
        "flow": np.asarray(flow, np.float32),
        "confidence": np.asarray(confidence, np.float32),
        "cluster": np.asarray(cluster, np.int32),
        "attrs": {
            "sample_id": pair.sample_id,
            "log_id": pair.log_id,
            "index": index,
            "timestamp0_ns": -1,
            "timestamp1_ns": -1,
            "dt": pair.dt,
        },
    }
    if with_gt:
        sample.update(
            gt_flow=pair.flow, gt_flow_valid=pair.flow_valid, gt_classes=pair.classes, gt_dynamic=pair.dynamic
        )
    return sample


def write_labels(
    out_dir: Path, shards: dict[str, list[dict]], config: str, config_hash: str, compression: str | None = None
) -> Path:
    """Write ``shards`` (``{file name: samples}``) into ``out_dir`` (created) with the labeller ``config`` text and
    its hash, and the ``index.json`` listing their samples; returns ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    for name, samples in shards.items():
        write_shard(out_dir / name, samples, config, config_hash, compression)
    records = {
        name: [
            {
                "sample_id": s["attrs"]["sample_id"],
                "index": s["attrs"]["index"],
                "n0": len(s["pc0"]),
                "n1": len(s["pc1"]),
            }
            for s in samples
        ]
        for name, samples in shards.items()
    }
    write_index(
        out_dir / "index.json",
        {"config_hash": config_hash, "shards": [{"file": name, "samples": rows} for name, rows in records.items()]},
    )
    return out_dir


def write_pseudo_labels(
    out_dir: Path,
    pairs,
    with_gt: bool = True,
    noise: float = 0.0,
    config: str = OmegaConf.to_yaml({"split": "train", "teacher": TEACHER.to_dict()}),
) -> Path:
    """One shard in the label.py layout whose pseudo-labels are the ground truth of ``pairs`` (plus Gaussian ``noise``
    in m; confidence 0 on ground, cluster 0 on foreground), with a labeller ``config`` as label.py writes it."""
    rng = np.random.default_rng(0)
    samples = [
        pair_sample(
            pair,
            index,
            pair.flow + rng.normal(0, noise, pair.flow.shape),
            np.where(pair.ground0, 0.0, 1.0),
            np.where(pair.classes > 0, 0, -1),
            with_gt,
        )
        for index, pair in enumerate(pairs)
    ]
    return write_labels(out_dir, {"shard_000000.h5": samples}, config, "test")
