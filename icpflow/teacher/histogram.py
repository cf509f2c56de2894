"""Step 5: histogram initialisation of a cluster pair's translation.

Every point pair (i, j) of a source cluster and a destination cluster votes for the translation
``dst_j - src_i`` in a 3D histogram: ``bin`` metres wide in x and y over ``[-window, window]``, ``z_bins`` bins
over ``[-z_range, z_range]`` in z. The histogram is max-pooled (cubic kernel ``nms_kernel``, cells outside the
histogram ignored), the ``top_k`` local maxima with a vote are kept, the zero translation is added, and each
candidate ``t`` is scored by the mean nearest-neighbour distance between ``src + t`` and ``dst``, computed in both
directions; the smaller of the two (as the reference does: it stays small when one cluster only partly overlaps
the other) is the score, and the candidate with the lowest score is returned.

Bins are centred on multiples of the bin size, so the zero translation is the centre of the middle bin and a
peak's translation is its bin CENTRE. The reference implementation returns the bin's lower edge instead (it adds
``bin // 2``, which is 0 for a 0.1 m bin), a systematic 5 cm bias in x and y that ICP then has to remove; its
CUDA vote also spreads ``2 * window / bin + 1`` bins over ``2 * window``, so its bins are slightly narrower than
the labels it reads them back with.

Extension for long, fast vehicles (``axis_min_extent`` > 0; off in the reference, on in every preset: BENCHMARKS.md,
"Teacher: speed and quality"): a source cluster at least that long along its main horizontal axis whose best
candidate moves it (by at least ``axis_step``) also gets a line search of its start along that axis
(:func:`_axis_search`). On a long vehicle seen from the side the vote's ridge runs along the axis
and its height follows the scan pattern (which moves with the sensor), not the object, so its peaks can fall metres
short of the true motion (a 10 m bus at 27 m/s: 1.8 m). Candidates every ``axis_step`` metres across the window are
scored as above on at most ``axis_points`` points per cluster, the best is refined in quarter steps on every point,
and it replaces the start when it scores lower. A start the vote finds static is left alone: along a featureless
wall the scan pattern, not the wall, would decide where it slides.

All points are in one common frame (the pipeline compensates ego motion first); shapes: clusters (N, 3).
"""

from __future__ import annotations

import numba
import numpy as np

from icpflow.teacher.config import HistogramConfig


def subsample(points: np.ndarray, cap: int, seed: int) -> np.ndarray:
    """At most ``cap`` rows of ``points`` (N, 3), drawn without replacement by a generator seeded with ``seed``.

    The same input always gives the same rows, in their original order.
    """
    if len(points) <= cap:
        return points
    keep = np.random.default_rng(seed).choice(len(points), cap, replace=False)
    return points[np.sort(keep)]


def pack(clouds: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Concatenate P clouds (N_p, 3) into one float64 (sum N_p, 3) array plus (P + 1,) int64 offsets."""
    offsets = np.zeros(len(clouds) + 1, dtype=np.int64)
    offsets[1:] = np.cumsum([len(c) for c in clouds])
    if offsets[-1] == 0:
        return np.zeros((0, 3)), offsets
    return np.concatenate([np.asarray(c, dtype=np.float64).reshape(-1, 3) for c in clouds]), offsets


@numba.njit(cache=True, nogil=True)
def _max_filter(values: np.ndarray, half: int) -> np.ndarray:
    """Maximum over the cube ``[-half, half]^3`` around each cell of a 3D array, cells outside ignored."""
    nx, ny, nz = values.shape
    a = np.empty_like(values)
    for i in range(nx):
        lo, hi = max(0, i - half), min(nx, i + half + 1)
        for j in range(ny):
            for k in range(nz):
                best = values[lo, j, k]
                for m in range(lo + 1, hi):
                    best = max(best, values[m, j, k])
                a[i, j, k] = best
    b = np.empty_like(values)
    for i in range(nx):
        for j in range(ny):
            lo, hi = max(0, j - half), min(ny, j + half + 1)
            for k in range(nz):
                best = a[i, lo, k]
                for m in range(lo + 1, hi):
                    best = max(best, a[i, m, k])
                b[i, j, k] = best
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                lo, hi = max(0, k - half), min(nz, k + half + 1)
                best = b[i, j, lo]
                for m in range(lo + 1, hi):
                    best = max(best, b[i, j, m])
                a[i, j, k] = best
    return a


@numba.njit(cache=True, nogil=True)
def _vote_peaks(src, dst, window, bin_size, z_bins, z_range, nms_kernel, top_k):
    """Top-k histogram peaks of ``dst_j - src_i``: ((k, 3) bin-centre translations, number of valid rows)."""
    half_xy = int(np.round(window / bin_size))
    nxy = 2 * half_xy + 1
    z_step = 2.0 * z_range / (z_bins - 1) if z_bins > 1 else 2.0 * z_range  # one bin: [-z_range, z_range]
    half_z = (z_bins - 1) / 2.0  # z bin k is centred on (k - half_z) * z_step
    hist = np.zeros((nxy, nxy, z_bins), dtype=np.int32)
    # Shifted so that a vote's bin index is the truncation of a non-negative float (cheaper than floor).
    inv_xy = 1.0 / bin_size
    inv_z = 1.0 / z_step
    off_xy = half_xy + 0.5
    off_z = half_z + 0.5
    # dst sorted by z: each source point only visits the dst points inside the z extent of the histogram.
    by_z = np.argsort(dst[:, 2], kind="mergesort")
    dst_x, dst_y, dst_z = dst[by_z, 0].copy(), dst[by_z, 1].copy(), dst[by_z, 2].copy()
    reach = off_z * z_step
    for i in range(src.shape[0]):
        sx, sy, sz = src[i, 0], src[i, 1], src[i, 2]
        for j in range(np.searchsorted(dst_z, sz - reach), np.searchsorted(dst_z, sz + reach)):
            fz = (dst_z[j] - sz) * inv_z + off_z
            fx = (dst_x[j] - sx) * inv_xy + off_xy
            fy = (dst_y[j] - sy) * inv_xy + off_xy
            if 0.0 <= fx < nxy and 0.0 <= fy < nxy and 0.0 <= fz < z_bins:
                hist[int(fx), int(fy), int(fz)] += 1
    half = nms_kernel // 2
    pooled = _max_filter(hist, half)
    counts = np.empty(hist.size, dtype=np.int64)
    flat = np.empty(hist.size, dtype=np.int64)
    n = 0
    for ix in range(nxy):
        for iy in range(nxy):
            for iz in range(z_bins):
                if hist[ix, iy, iz] > 0 and hist[ix, iy, iz] == pooled[ix, iy, iz]:
                    counts[n] = hist[ix, iy, iz]
                    flat[n] = (ix * nxy + iy) * z_bins + iz
                    n += 1
    # Stable sort on descending count: equal counts keep ascending bin order, so the result is deterministic.
    order = np.argsort(-counts[:n], kind="mergesort")
    k = min(top_k, n)
    peaks = np.zeros((top_k, 3))
    for r in range(k):
        f = flat[order[r]]
        iz = f % z_bins
        iy = (f // z_bins) % nxy
        ix = f // (z_bins * nxy)
        peaks[r, 0] = (ix - half_xy) * bin_size
        peaks[r, 1] = (iy - half_xy) * bin_size
        peaks[r, 2] = (iz - half_z) * z_step
    return peaks, k


# fastmath without the no-inf / no-nan assumptions: min() against infinity stays exact.
@numba.njit(cache=True, nogil=True, fastmath={"reassoc", "contract", "arcp", "nsz"})
def _scores(src_t, dst_t, candidates):
    """Score of each candidate translation (K, 3): the smaller of the two directed mean nearest-neighbour distances
    between ``src + t`` and ``dst``. Clusters are given transposed, (3, Ns) and (3, Nd), for vectorised loops."""
    ns, nd = src_t.shape[1], dst_t.shape[1]
    out = np.empty(candidates.shape[0])
    col = np.empty(nd)
    for c in range(candidates.shape[0]):
        col[:] = np.inf
        fwd = 0.0
        for i in range(ns):
            x = src_t[0, i] + candidates[c, 0]
            y = src_t[1, i] + candidates[c, 1]
            z = src_t[2, i] + candidates[c, 2]
            row = np.inf
            for j in range(nd):
                d = (dst_t[0, j] - x) ** 2 + (dst_t[1, j] - y) ** 2 + (dst_t[2, j] - z) ** 2
                row = min(row, d)
                col[j] = min(col[j], d)
            fwd += np.sqrt(row)
        bwd = 0.0
        for j in range(nd):
            bwd += np.sqrt(col[j])
        out[c] = min(fwd / ns, bwd / nd)
    return out


@numba.njit(cache=True, nogil=True)
def main_axis(points):
    """(unit (2,) main horizontal axis of (N >= 1, 3) float64 points, their length along it in metres)."""
    n = points.shape[0]
    mx, my = points[:, 0].mean(), points[:, 1].mean()
    sxx = sxy = syy = 0.0
    for i in range(n):
        dx, dy = points[i, 0] - mx, points[i, 1] - my
        sxx += dx * dx
        sxy += dx * dy
        syy += dy * dy
    angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # direction of the larger eigenvalue of the 2x2 covariance
    axis = np.array([np.cos(angle), np.sin(angle)])
    low, high = np.inf, -np.inf
    for i in range(n):
        along = points[i, 0] * axis[0] + points[i, 1] * axis[1]
        low, high = min(low, along), max(high, along)
    return axis, high - low


@numba.njit(cache=True, nogil=True)
def _axis_search(src, dst, axis, start, score, window, axis_step, axis_points):
    """The line search along the source cluster's main horizontal axis from ``start`` (its ``score``): candidates
    every ``axis_step`` metres across the window, scored on every k-th point (at most ``axis_points`` per
    cluster), then the best one refined in quarter steps on every point. Returns the best translation of all and its
    score (``start`` when nothing scores lower)."""
    axis, _ = main_axis(src)
    n_steps = int(window / axis_step)
    line = np.zeros((2 * n_steps + 1, 3))
    for s in range(-n_steps, n_steps + 1):
        line[s + n_steps, 0] = start[0] + s * axis_step * axis[0]
        line[s + n_steps, 1] = start[1] + s * axis_step * axis[1]
        line[s + n_steps, 2] = start[2]
    src_step = max(1, src.shape[0] // axis_points)
    dst_step = max(1, dst.shape[0] // axis_points)
    coarse = _scores(np.ascontiguousarray(src[::src_step].T), np.ascontiguousarray(dst[::dst_step].T), line)
    centre = line[np.argmin(coarse)]
    fine = np.zeros((9, 3))
    for q in range(9):
        fine[q, 0] = centre[0] + (q - 4) * 0.25 * axis_step * axis[0]
        fine[q, 1] = centre[1] + (q - 4) * 0.25 * axis_step * axis[1]
        fine[q, 2] = centre[2]
    scores = _scores(np.ascontiguousarray(src.T), np.ascontiguousarray(dst.T), fine)
    best = np.argmin(scores)
    if scores[best] < score:
        return fine[best], scores[best]
    return start, score


@numba.njit(cache=True, nogil=True)
def _initial_translation(
    src, dst, window, bin_size, z_bins, z_range, nms_kernel, top_k, axis_min_extent, axis_step, axis_points
):
    """Best candidate of one pair: ((3,) translation, score)."""
    peaks, k = _vote_peaks(src, dst, window, bin_size, z_bins, z_range, nms_kernel, top_k)
    candidates = np.zeros((k + 1, 3))  # the last row is the zero translation
    candidates[:k] = peaks[:k]
    scores = _scores(np.ascontiguousarray(src.T), np.ascontiguousarray(dst.T), candidates)
    c = np.argmin(scores)  # first minimum: ties go to the higher-voted peak
    moving = candidates[c, 0] ** 2 + candidates[c, 1] ** 2 >= axis_step**2  # the vote's best is not (near) zero
    if axis_min_extent > 0 and moving and src.shape[0] > 1:
        axis, extent = main_axis(src)
        if extent >= axis_min_extent:
            return _axis_search(src, dst, axis, candidates[c], scores[c], window, axis_step, axis_points)
    return candidates[c], scores[c]


@numba.njit(cache=True, nogil=True, parallel=True)
def _initial_translations(
    src_all,
    src_off,
    dst_all,
    dst_off,
    windows,
    bin_size,
    z_bins,
    z_range,
    nms_kernel,
    top_k,
    axis_min_extent,
    axis_step,
    axis_points,
    n_workers,
):
    """:func:`_initial_translation` for P packed pairs: ((P, 3) translations, (P,) scores). Worker w takes pairs
    w, w + n_workers, ...: with pairs sorted by decreasing cost this balances the load, which numba's contiguous
    split of a prange does not."""
    n_pairs = windows.shape[0]
    best = np.zeros((n_pairs, 3))
    score = np.full(n_pairs, np.inf)
    for w in numba.prange(n_workers):
        for p in range(w, n_pairs, n_workers):
            src = src_all[src_off[p] : src_off[p + 1]]
            dst = dst_all[dst_off[p] : dst_off[p + 1]]
            if src.shape[0] > 0 and dst.shape[0] > 0:
                best[p], score[p] = _initial_translation(
                    src,
                    dst,
                    windows[p],
                    bin_size,
                    z_bins,
                    z_range,
                    nms_kernel,
                    top_k,
                    axis_min_extent,
                    axis_step,
                    axis_points,
                )
    return best, score


def initial_translations(
    pairs: list[tuple[np.ndarray, np.ndarray]], windows: np.ndarray, params: HistogramConfig, seed: int = 0
) -> tuple[np.ndarray, np.ndarray]:
    """Histogram translations for P cluster pairs: ((P, 3) float64 src -> dst translations, (P,) scores in metres).

    ``pairs`` holds (src (Ns, 3), dst (Nd, 3)) in one frame, ``windows`` (P,) the x/y search half-width in metres;
    clusters are capped at ``params.max_points`` by a subsample seeded with ``seed``. A pair with an empty cluster
    gets the zero translation and an infinite score. A window wider than the vote holds is held at
    ``params.largest_window()`` (the teacher's pipeline says so where it widens one).
    """
    windows = np.minimum(np.asarray(windows, dtype=np.float64).reshape(-1), params.largest_window())
    if len(windows) != len(pairs):
        raise ValueError(f"initial_translations: {len(pairs)} pairs but {len(windows)} windows")
    if not pairs:
        return np.zeros((0, 3)), np.zeros(0)
    srcs = [subsample(np.asarray(s, np.float64).reshape(-1, 3), int(params.max_points), seed) for s, _ in pairs]
    dsts = [subsample(np.asarray(d, np.float64).reshape(-1, 3), int(params.max_points), seed) for _, d in pairs]
    order = np.argsort([-len(s) * len(d) for s, d in zip(srcs, dsts)], kind="stable")  # costly pairs first
    src_all, src_off = pack([srcs[k] for k in order])
    dst_all, dst_off = pack([dsts[k] for k in order])
    best, score = _initial_translations(
        src_all,
        src_off,
        dst_all,
        dst_off,
        windows[order],
        float(params.bin_size),
        int(params.z_bins),
        float(params.z_range),
        int(params.nms_kernel),
        int(params.top_k),
        float(params.axis_min_extent),
        float(params.axis_step),
        int(params.axis_points),
        numba.get_num_threads(),
    )
    translations, scores = np.empty_like(best), np.empty_like(score)
    translations[order], scores[order] = best, score
    return translations, scores


def initial_translation(
    src: np.ndarray, dst: np.ndarray, window_xy: float, params: HistogramConfig, seed: int = 0
) -> tuple[np.ndarray, float]:
    """Histogram translation (3,) float64 taking src (Ns, 3) onto dst (Nd, 3), and its score (metres)."""
    translations, scores = initial_translations([(src, dst)], np.array([window_xy]), params, seed)
    return translations[0], float(scores[0])


def centroid_translation(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The ``init=centroid`` ablation: (3,) float64 difference of the cluster centroids, dst minus src."""
    if len(src) == 0 or len(dst) == 0:
        return np.zeros(3)
    return np.asarray(dst, np.float64).mean(axis=0) - np.asarray(src, np.float64).mean(axis=0)
