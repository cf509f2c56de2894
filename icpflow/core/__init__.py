"""What every part of both packages stands on: the conventions (``geometry``: frames, units and transforms;
``frame_pair``: the FramePair record every reader returns), configuration rules (``settings``), errors and signals,
atomic writes, the console, threads and the CPU's abilities (``threads``, ``hardware``), Hydra's entry points, the
one door to open3d and the deprecation shims' helper. Imports nothing of icpflow's other rooms."""
