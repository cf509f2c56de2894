"""ZeroFlow dumps of Argoverse 2 pairs: NaN-padded files in the dump's layout from a hand-built rigid scene."""

import numpy as np

from icpflow.core.geometry import make_transform, transform_points

LOG = "0b86f508-5df9-4a46-bc59-5b9536dbde9f"
RNG = np.random.default_rng(3)
STATIC = RNG.uniform((-40, -40, -1.0), (40, 40, 3.0), (200, 3))
CAR = RNG.uniform((8, 2, -1.0), (12, 4, 0.5), (50, 3))
CAR_MOTION = make_transform(yaw=0.01, translation=(1.0, 0.0, 0.0))  # 10 m/s over 0.1 s, in the common frame


def dump_arrays(pad0=20, pad1=30, index_kind="indices") -> dict:
    """pc1 = static + car, pc2 = static + moved car (same rows), each NaN-padded after the valid rows."""
    pc1 = np.concatenate([STATIC, CAR])
    pc2 = np.concatenate([STATIC, transform_points(CAR_MOTION, CAR)])
    flow = pc2 - pc1
    classes = np.r_[np.full(len(STATIC), -1), np.full(len(CAR), 18)]  # REGULAR_VEHICLE, 0-based
    nan0, nan1 = np.full((pad0, 3), np.nan), np.full((pad1, 3), np.nan)
    valid0 = np.arange(len(pc1)) if index_kind == "indices" else np.r_[np.ones(len(pc1), bool), np.zeros(pad0, bool)]
    return {
        "pc1": np.concatenate([pc1, nan0]).astype(np.float32),
        "pc2": np.concatenate([pc2, nan1]).astype(np.float32),
        "gt_flow_0_1": np.concatenate([flow, nan0]).astype(np.float32),
        "pc1_flows_valid_idx": valid0,
        "pc2_flows_valid_idx": np.arange(len(pc2)),
        "pc1_classes": np.r_[classes, np.full(pad0, -1)].astype(np.int64),
        "pc2_classes": np.r_[classes, np.full(pad1, -1)].astype(np.int64),
    }


def write_dump(root, name="000007", **changes):
    folder = root / "val_zero_flow" / LOG
    folder.mkdir(parents=True, exist_ok=True)
    arrays = {key: value for key, value in {**dump_arrays(), **changes}.items() if value is not None}
    np.savez(folder / f"{name}.npz", **arrays)
    return folder / f"{name}.npz"
