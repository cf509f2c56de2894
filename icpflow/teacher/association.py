"""Step 8: choose which candidate cluster pairs become matches.

* ``argmin`` (the reference): for each source cluster, its passing pair with the smallest cost; several source
  clusters may pick the same destination cluster. Ties go to the pair listed first.
* ``hungarian``: a one-to-one assignment minimising the total cost over passing pairs
  (``scipy.optimize.linear_sum_assignment``).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

METHODS = ("argmin", "hungarian")


def associate(
    src_ids: np.ndarray, dst_ids: np.ndarray, cost: np.ndarray, passes: np.ndarray, method: str = "argmin"
) -> np.ndarray:
    """(P,) bool: the chosen pairs among P candidates (src_ids[p], dst_ids[p]) with finite ``cost`` (P,).

    Pairs that do not pass are never chosen. With ``hungarian``, duplicate (src, dst) pairs compete and the first
    with the smallest cost represents them.
    """
    src_ids = np.asarray(src_ids).reshape(-1)
    dst_ids = np.asarray(dst_ids).reshape(-1)
    cost = np.asarray(cost, dtype=np.float64).reshape(-1)
    passes = np.asarray(passes, dtype=bool).reshape(-1)
    n_pairs = len(src_ids)
    if not (len(dst_ids) == len(cost) == len(passes) == n_pairs):
        raise ValueError(
            f"associate: lengths differ (src_ids {n_pairs}, dst_ids {len(dst_ids)}, cost {len(cost)}, "
            f"passes {len(passes)})"
        )
    if method not in METHODS:
        raise ValueError(f"associate: method must be one of {METHODS}, got {method!r}")
    candidates = np.flatnonzero(passes & np.isfinite(cost))
    chosen = np.zeros(n_pairs, dtype=bool)
    if len(candidates) == 0:
        return chosen
    # Stable order by (cost, position): the first entry per group is its best pair, ties to the earliest.
    ranked = candidates[np.lexsort((candidates, cost[candidates]))]
    if method == "argmin":
        _, first = np.unique(src_ids[ranked], return_index=True)
        chosen[ranked[first]] = True
        return chosen
    src_u, src_row = np.unique(src_ids[ranked], return_inverse=True)
    dst_u, dst_col = np.unique(dst_ids[ranked], return_inverse=True)
    best = np.full((len(src_u), len(dst_u)), -1, dtype=np.int64)
    for p, r, c in zip(ranked[::-1], src_row[::-1], dst_col[::-1]):  # reversed: the best pair is written last
        best[r, c] = p
    # Missing pairs get a cost no assignment of real pairs can beat, then are dropped from the answer.
    big = 1.0 + 2.0 * np.abs(cost[candidates]).sum() * max(len(src_u), len(dst_u))
    matrix = np.where(best >= 0, cost[np.maximum(best, 0)], big)
    rows, cols = linear_sum_assignment(matrix)
    picked = best[rows, cols]
    chosen[picked[picked >= 0]] = True
    return chosen
