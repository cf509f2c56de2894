"""Bird's-eye-view pictures of a frame pair and its flow (matplotlib, headless).

All panels are drawn in the ego frame of t + dt (pc1's frame), x forward to the right, y to the left upwards.
Flow colour encodes the RESIDUAL (ego-compensated) flow, because full flow is dominated by the ego motion:
hue = direction in the xy-plane, from grey (still) to full colour at ``max_speed`` m/s.
"""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import hsv_to_rgb  # noqa: E402

from icpflow.frames import FramePair  # noqa: E402
from icpflow.geometry import full_to_residual, transform_points  # noqa: E402


def flow_colours(residual: np.ndarray, dt: float, max_speed: float = 10.0) -> np.ndarray:
    """(N, 3) RGB in [0, 1] for (N, 3) residual flow: hue = xy direction, mixed from grey (still) to the full hue
    at ``max_speed`` m/s (square-root ramp, so that slow movers already stand out)."""
    angle = np.arctan2(residual[:, 1], residual[:, 0])
    speed = np.linalg.norm(residual[:, :2], axis=1) / dt
    hue = hsv_to_rgb(np.stack([(angle + np.pi) / (2 * np.pi), np.ones_like(angle), np.full_like(angle, 0.9)], axis=1))
    weight = np.sqrt(np.clip(speed / max_speed, 0.0, 1.0))[:, None]
    return weight * hue + (1.0 - weight) * 0.6


def _scatter(ax, points, colour, size, label=None):
    ax.scatter(points[:, 0], points[:, 1], s=size, c=colour, linewidths=0, label=label, rasterized=True)


def plot_bev(
    pair: FramePair,
    path: str | os.PathLike,
    predicted: np.ndarray | None = None,
    extent: float = 40.0,
    max_speed: float = 10.0,
    title: str = "",
) -> Path:
    """Write a BEV PNG of ``pair`` to ``path``; ``predicted`` is (N0, 3) FULL flow. Returns the path.

    Panels: pc0 (moved by ego motion) and pc1; pc0 + predicted flow against pc1; pc0 + ground-truth flow against
    pc1 (if the pair has it); predicted and ground-truth residual flow coloured by direction and speed.
    Ground points, when ``ground0`` is known, are drawn light grey in the flow panels.
    """
    ego = pair.ego1_from_ego0 if pair.ego1_from_ego0 is not None else np.eye(4)
    flows = [("predicted", predicted)] if predicted is not None else []
    if pair.flow is not None:
        flows.append(("ground truth", pair.flow))
    panels = 1 + 2 * len(flows)
    cols = min(panels, 3)
    rows = int(np.ceil(panels / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 6 * rows), squeeze=False)
    size = 0.3
    ground = pair.ground0 if pair.ground0 is not None else np.zeros(len(pair.pc0), bool)

    ax = axes.flat[0]
    _scatter(ax, pair.pc1, "tab:red", size, "pc1")
    _scatter(ax, transform_points(ego, pair.pc0), "tab:blue", size, "pc0 (ego-compensated)")
    ax.set_title("pc0 (blue, ego-compensated) and pc1 (red)")
    index = 1
    for name, flow in flows:
        ax = axes.flat[index]
        _scatter(ax, pair.pc1, "tab:red", size)
        _scatter(ax, pair.pc0 + flow, "tab:green", size)
        ax.set_title(f"pc0 + {name} flow (green) and pc1 (red)")
        ax = axes.flat[index + 1]
        residual = full_to_residual(flow, pair.pc0, ego)
        moved = transform_points(ego, pair.pc0)
        _scatter(ax, moved[ground], "0.85", size)
        colours = flow_colours(residual[~ground], pair.dt, max_speed)
        _scatter(ax, moved[~ground], colours, size * 2)
        ax.set_title(f"{name} residual flow (hue: direction; grey: still, full colour: {max_speed:g} m/s)")
        index += 2
    for ax in axes.flat[:panels]:
        ax.set_xlim(-extent, extent)
        ax.set_ylim(-extent, extent)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_facecolor("white")
    for ax in axes.flat[panels:]:
        ax.axis("off")
    fig.suptitle(title or pair.sample_id or "frame pair")
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp.png")
    fig.savefig(tmp, dpi=80)
    plt.close(fig)
    os.replace(tmp, path)
    return path
