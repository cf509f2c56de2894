"""Pictures of a frame pair and its flow, headless: bird's-eye views (matplotlib) and 3D renders (open3d).

Everything is drawn in the ego frame of t + dt (pc1's frame); BEV panels have x forward to the right, y to the left
upwards. pc0 moved by the ego motion is blue, pc1 red, pc0 + flow green (``PC0_COLOUR``, ``PC1_COLOUR``,
``MOVED_COLOUR``). Flow colour encodes the RESIDUAL (ego-compensated) flow, because full flow is dominated by the
ego motion: hue = direction in the xy-plane, from grey (still) to full colour at ``max_speed`` m/s.
"""

from __future__ import annotations

import contextlib
import functools
import os
import re
import subprocess
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import hsv_to_rgb, to_rgb, to_rgba_array  # noqa: E402

from icpflow.core.atomic import atomic_path  # noqa: E402
from icpflow.core.console import captured_output  # noqa: E402
from icpflow.core.frame_pair import FramePair  # noqa: E402
from icpflow.core.geometry import full_to_residual, transform_points  # noqa: E402

PC0_COLOUR, PC1_COLOUR, MOVED_COLOUR = to_rgb("tab:blue"), to_rgb("tab:red"), to_rgb("tab:green")


def flow_colours(residual: np.ndarray, dt: float, max_speed: float = 10.0) -> np.ndarray:
    """(N, 3) RGB in [0, 1] for (N, 3) residual flow: hue = xy direction, mixed from grey (still) to the full hue
    at ``max_speed`` m/s (square-root ramp, so that slow movers already stand out)."""
    angle = np.arctan2(residual[:, 1], residual[:, 0])
    speed = np.linalg.norm(residual[:, :2], axis=1) / dt
    hue = hsv_to_rgb(np.stack([(angle + np.pi) / (2 * np.pi), np.ones_like(angle), np.full_like(angle, 0.9)], axis=1))
    weight = np.sqrt(np.clip(speed / max_speed, 0.0, 1.0))[:, None]
    return weight * hue + (1.0 - weight) * 0.6


def _scatter(ax, points, colour, size, label=None):
    ax.scatter(points[:, 0], points[:, 1], s=size, c=to_rgba_array(colour), linewidths=0, label=label, rasterized=True)


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
    _scatter(ax, pair.pc1, PC1_COLOUR, size, "pc1")
    _scatter(ax, transform_points(ego, pair.pc0), PC0_COLOUR, size, "pc0 (ego-compensated)")
    ax.set_title("pc0 (blue, ego-compensated) and pc1 (red)")
    index = 1
    for name, flow in flows:
        ax = axes.flat[index]
        _scatter(ax, pair.pc1, PC1_COLOUR, size)
        _scatter(ax, pair.pc0 + flow, MOVED_COLOUR, size)
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
    try:
        with atomic_path(path, make_parents=True) as tmp:
            fig.savefig(tmp, dpi=80)
    finally:
        plt.close(fig)
    return Path(path)


#: what open3d's offscreen renderer (Filament on Vulkan) prints for every renderer it makes, on a healthy machine
RENDERER_BANNER = re.compile(
    r"(\x1b\[[0-9;]*m)*(\[Open3D INFO\]|\[Open3D WARNING\] GLFWWindowSystem: X11 GLFW init failed|Using 'soft' "
    r"CircularBuffer|FEngine |Vulkan device driver:|Selected physical device|Backend feature level:)"
)


@contextlib.contextmanager
def _renderer_output():
    """Catch what C++ libraries write to file descriptors 1 and 2 for the duration, then pass on to stderr every
    line that is not ``RENDERER_BANNER`` (so stdout keeps eval.py's tables, and real warnings still show)."""
    lines: list[str] = []
    try:
        with captured_output((1, 2)) as lines:
            yield
    finally:
        kept = [line for line in lines if line.strip() and not RENDERER_BANNER.match(line)]
        if kept:
            print("\n".join(kept), file=sys.stderr, flush=True)


_PROBE = (
    "from icpflow.core.open3d_loader import load_open3d; "
    "load_open3d().visualization.rendering.OffscreenRenderer(16, 16).render_to_image()"
)


@functools.cache
def offscreen_problem() -> str | None:
    """None if open3d can render offscreen here, else a one-line reason. Probed once per process in a child
    process, because open3d aborts the whole process when it finds no Vulkan driver."""
    try:
        done = subprocess.run([sys.executable, "-c", _PROBE], capture_output=True, text=True, timeout=300)
    except subprocess.TimeoutExpired:
        return "open3d offscreen rendering did not start within 300 s"
    if done.returncode == 0:
        return None
    lines = [line.strip() for line in (done.stdout + done.stderr).splitlines() if line.strip()]
    return (
        f"open3d offscreen rendering is unavailable here ({lines[-1] if lines else f'exit {done.returncode}'}); "
        "it needs libusb-1.0-0, libvulkan1 and mesa-vulkan-drivers"
    )


def render_pair(
    pair: FramePair,
    path: str | os.PathLike,
    predicted: np.ndarray | None = None,
    size: tuple[int, int] = (1280, 720),
    extent: float = 40.0,
    point_size: float = 2.0,
) -> Path:
    """Write an open3d offscreen render of ``pair`` to the PNG ``path``, ``size`` = (width, height) pixels.

    In the ego frame of t + dt: pc0 moved by the ego motion (blue), pc1 (red) and pc0 + ``predicted`` (N0, 3)
    FULL flow (green; the ground truth when None, left out without either), points within ``extent`` m in x and
    y, seen from behind and above the ego vehicle. Unlit, no post-processing: the points have exactly these
    colours on white. Call :func:`offscreen_problem` first (without Vulkan open3d aborts the process).
    """
    from icpflow.core.open3d_loader import load_open3d

    o3d = load_open3d()
    rendering = o3d.visualization.rendering
    ego = pair.ego1_from_ego0 if pair.ego1_from_ego0 is not None else np.eye(4)
    flow = predicted if predicted is not None else pair.flow
    clouds = [("pc0", transform_points(ego, pair.pc0), PC0_COLOUR), ("pc1", pair.pc1, PC1_COLOUR)]
    if flow is not None:
        clouds.append(("pc0 + flow", pair.pc0 + flow, MOVED_COLOUR))
    width, height = (int(v) for v in size)
    with _renderer_output():  # its engine logs a banner to stdout per renderer; keep stdout for the tables
        renderer = rendering.OffscreenRenderer(width, height)
        renderer.scene.set_background([1.0, 1.0, 1.0, 1.0])
        renderer.scene.view.set_post_processing(False)  # no tone mapping: colours stay exact
        material = rendering.MaterialRecord()
        material.shader, material.point_size = "defaultUnlit", float(point_size)
        for name, points, colour in clouds:
            inside = points[np.abs(points[:, :2]).max(axis=1) <= extent]
            if len(inside):
                cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(inside.astype(np.float64)))
                cloud.paint_uniform_color(colour)
                renderer.scene.add_geometry(name, cloud, material)
        renderer.setup_camera(60.0, [0.3 * extent, 0.0, 0.0], [-0.8 * extent, 0.0, 0.6 * extent], [0.0, 0.0, 1.0])
        image = renderer.render_to_image()
    with atomic_path(path, make_parents=True) as tmp:
        if not o3d.io.write_image(str(tmp), image):
            raise OSError(f"{path}: open3d could not write the render")
    return Path(path)
