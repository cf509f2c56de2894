"""Trivial scene-flow baselines returning (N0, 3) float32 FULL flow for a FramePair."""

import numpy as np


def zero_flow(pair) -> np.ndarray:
    """Full flow 0: every point assumed fixed in the sensor frame."""
    return np.zeros((len(pair.pc0), 3), np.float32)


def ego_only_flow(pair) -> np.ndarray:
    """Full flow = ego flow: every point assumed static in the world (needs pair.ego1_from_ego0)."""
    return pair.ego_flow().astype(np.float32)
