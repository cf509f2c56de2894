"""Pictures of frame pairs and their flow: bird's-eye views and 3D renders (``pictures``), recordings for the rerun
viewer (``recording``).

``icpflow.viz`` was a module in the last release: its names are answered from ``pictures`` with a
``DeprecationWarning`` until 0.3."""

from icpflow.core.deprecation import moved_attribute

#: the old module's names, and where each lives today
MOVED = {
    name: "icpflow.viz.pictures"
    for name in ("RENDERER_BANNER", "flow_colours", "offscreen_problem", "plot_bev", "render_pair")
}


def __getattr__(name: str):
    return moved_attribute("icpflow.viz", name, MOVED)
