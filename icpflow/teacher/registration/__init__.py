"""Step 6: rigid registration of cluster pairs, the small public API the teacher and the student's refinement share.

- :func:`register_clusters` (``batch``): a batch of cluster pairs from their initial translations, on the backend the
  ICP settings name (``cpu``: numba, parallel over pairs; ``torch_batch``: a padded batch for GPUs), and the match
  quality the checks read (:class:`RegistrationResult`);
- :func:`register_stages_cpu` and :func:`grid_cell` (``cpu``): the refinement's batched ICP over several starts;
- ``icp``: the ICP variants on one pair (point-to-point, point-to-plane) and their settings.
"""

from icpflow.teacher.registration.batch import RegistrationResult, plane_errors, register_clusters, register_plane
from icpflow.teacher.registration.cpu import grid_cell, register_batch_cpu, register_stages_cpu

__all__ = [
    "RegistrationResult",
    "grid_cell",
    "plane_errors",
    "register_batch_cpu",
    "register_clusters",
    "register_plane",
    "register_stages_cpu",
]
