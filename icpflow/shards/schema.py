"""Shard schema: one HDF5 file per run of consecutive samples, one group per sample.

Group ``samples/<k>`` (k = position in the shard, zero-padded) holds ``pc0`` (N0, 3) / ``pc1`` (N1, 3) float32
(the scans as read, ego frames of t and t + dt), ``ground0`` (N0,) / ``ground1`` (N1,) bool, ``ego1_from_ego0``
(4, 4) float64, ``flow`` (N0, 3) float32 pseudo-label FULL flow, ``confidence`` (N0,) float32, ``cluster`` (N0,)
int32, and optionally ``gt_flow`` (N0, 3) float32, ``gt_flow_valid`` (N0,) bool, ``gt_classes`` (N0,) int32,
``gt_dynamic`` (N0,) bool. Group attributes: ``sample_id``, ``log_id``, ``index`` (dataset index),
``timestamp0_ns``, ``timestamp1_ns`` (-1 when unknown), ``dt``. File attributes: ``config`` (YAML), ``config_hash``,
``package_version``, ``schema_version``, ``num_samples``.
"""

SCHEMA_VERSION = 1
#: the ``compression`` settings of the writer (HDF5 filters; none = uncompressed)
COMPRESSIONS = ("none", "gzip", "lzf")

#: dataset name -> (dtype, trailing shape; None = per point of the named cloud)
REQUIRED = {
    "pc0": ("float32", 3),
    "pc1": ("float32", 3),
    "ground0": ("bool", None),
    "ground1": ("bool", None),
    "ego1_from_ego0": ("float64", (4, 4)),
    "flow": ("float32", 3),
    "confidence": ("float32", None),
    "cluster": ("int32", None),
}
OPTIONAL = {
    "gt_flow": ("float32", 3),
    "gt_flow_valid": ("bool", None),
    "gt_classes": ("int32", None),
    "gt_dynamic": ("bool", None),
}
#: which cloud a per-point array follows
CLOUD = {"pc1": "pc1", "ground1": "pc1"}
SAMPLE_ATTRS = ("sample_id", "log_id", "index", "timestamp0_ns", "timestamp1_ns", "dt")
FILE_ATTRS = ("config", "config_hash", "package_version", "schema_version", "num_samples")


def group_name(position: int) -> str:
    """HDF5 path of the position-th sample of a shard."""
    return f"samples/{position:05d}"


def shard_name(shard: int) -> str:
    """File name of shard number ``shard``."""
    return f"shard_{shard:06d}.h5"
