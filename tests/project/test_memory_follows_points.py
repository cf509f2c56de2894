"""Memory follows the number of points, not where they are: a pair with five stray returns 30 km out is
computed by the teacher and by the refining Predictor in about the memory of the same pair without them (the
neighbour grids, the refinement's components and boxes bounded by the points: ``icpflow.scans.neighbours``,
``fastflow3d.inference.refine.sparse_components``, ``icpflow.scans.bev``); the structures sized by options refuse a
size they could not hold, in one line naming the options. Each run is a child process whose peak memory is read."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from icpflow.scans.neighbours import build_grid, k_nearest, nearest
from icpflow.teacher.config import ICPFlowConfig

from helpers.data import REPO

CHILD = """
import resource, sys, time
import numpy as np
from icpflow.datasets.synthetic import SyntheticDataset
from icpflow.teacher import ICPFlow, ICPFlowConfig
from fastflow3d import Predictor

far = float(sys.argv[1])
pair = SyntheticDataset(split="test", num_sequences=1, frames_per_sequence=2, beams=32, seed=0)[0]
pc0, pc1 = pair.pc0.copy(), pair.pc1.copy()
if far:
    strays = np.array([[far, far, 0.5], [-far, far, 1.0], [far, -far, 2.0], [0.3 * far, far, 0.0], [far, 0.0, 3.0]])
    pc0 = np.concatenate([pc0, strays.astype(np.float32)])
    pc1 = np.concatenate([pc1, strays.astype(np.float32)])
start = time.perf_counter()
flow = ICPFlow(ICPFlowConfig.preset("waymo"))(pc0, pc1).flow
predicted = Predictor.load(refine=True).predict(pc0, pc1).flow
assert flow.shape == pc0.shape and np.isfinite(flow).all() and np.isfinite(predicted).all()
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, time.perf_counter() - start)
"""


def peak(far: float) -> tuple[float, float]:
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(CHILD), str(far)], cwd=REPO, capture_output=True, text=True,
        timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-1500:]
    megabytes, seconds = map(float, done.stdout.split())
    return megabytes, seconds


@pytest.mark.slow
def test_stray_returns_far_out_cost_no_memory():
    base, took = peak(0.0)
    for far in (30_000.0,):
        used, seconds = peak(far)
        assert used < base + 300, (far, used, base)  # MB: a MemoryError at 30 km before (6.8 GB at 10 km)
        assert seconds < 3 * took + 10, (far, seconds, took)  # was 20 s against 6 s


def test_a_grid_of_far_flung_points_stays_exact_and_small():
    """Nearest neighbours on a cloud with strays kilometres out: the grid is bounded (its columns a few per point)
    and every answer is the brute-force one, for queries inside, at the border and out by the strays."""
    rng = np.random.default_rng(0)
    points = np.concatenate([rng.uniform(-20, 20, (4000, 3)), [[10_000, 10_000, 0], [-30_000, 5, 1], [7, 8, 20_000]]])
    cell = 0.1
    grid = build_grid(points, cell)
    dims, starts = grid[1], grid[2]
    assert dims[3] == 1 and len(starts) <= max(1 << 20, 4 * len(points)) + 1
    queries = np.concatenate([rng.uniform(-25, 25, (300, 3)), points[-3:] + 0.05, [[10_001, 9_999, 0.2]]])
    for q in queries:
        j, d2 = nearest(q, points, grid, cell, np.inf)
        truth = ((points - q) ** 2).sum(axis=1)
        assert d2 == truth.min() and truth[j] == d2
    best_d2, best_j = k_nearest(queries, points, grid, cell, 5, np.inf, 8, True)
    for q, d2 in zip(queries, best_d2):
        np.testing.assert_array_equal(np.sort(((points - q) ** 2).sum(axis=1))[:5], d2)
    normal = rng.uniform(-20, 20, (4000, 3))  # an ordinary cloud keeps its bounding box: nothing changes
    assert build_grid(normal, cell)[1][3] == 0


@pytest.mark.parametrize(
    "override, words",
    [
        ({"ground.cell": 0.001}, "ground.cell or lower ground.patchwork_max_range"),
        ({"ground.patchwork_max_range": 100_000.0}, "ground.cell or lower ground.patchwork_max_range"),
        ({"histogram.bin_size": 0.0001}, "raise histogram.bin_size"),
        ({"pairing.speed": 5000.0}, "raise histogram.bin_size"),
        ({"histogram.axis_step": 1e-7}, "raise histogram.axis_step"),
    ],
)
def test_options_that_size_a_structure_are_bounded(override, words):
    with pytest.raises(ValueError, match=words) as raised:
        ICPFlowConfig.preset("av2", **override)
    assert "\n" not in str(raised.value) and "it may hold" in str(raised.value)


EGO_CHILD = """
import resource, sys
import numpy as np
resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))
from icpflow.datasets.synthetic import SyntheticDataset
from icpflow.teacher import ICPFlow, ICPFlowConfig
pair = SyntheticDataset(split="test", num_sequences=1, frames_per_sequence=2, beams=32, seed=0)[0]
ego = np.eye(4)
ego[0, 3] = 300.0
flow = ICPFlow(ICPFlowConfig.preset("waymo"))(pair.pc0, pair.pc1, ego1_from_ego0=ego).flow
assert flow.shape == pair.pc0.shape and np.isfinite(flow).all()
"""


def test_a_given_ego_motion_far_too_long_holds_the_search_window():
    """A pose of 300 m between two scans (a wrong poses file) widens the teacher's search window, which sizes every
    cluster pair's vote: it is held at the widest the vote holds, with one warning, within 4 GB (a MemoryError
    inside the vote's kernel before)."""
    done = subprocess.run([sys.executable, "-c", EGO_CHILD], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-1500:]
    assert "an ego motion of 300.0 m between the scans widens the search window to 600.0 m; held at 59.0 m" in (
        done.stderr
    ), done.stderr[-1500:]


def test_the_vote_holds_any_window_it_is_given():
    """``histogram.initial_translations`` called with a 5 km window (a caller of the registration API) votes within
    the widest window it holds and finds the translation (zero and an infinite score before: the vote did not fit)."""
    from icpflow.teacher import histogram
    from icpflow.teacher.config import HistogramConfig

    src = np.random.default_rng(0).normal(size=(500, 3))
    translations, scores = histogram.initial_translations([(src, src + [1.0, 0.5, 0.0])], [5000.0], HistogramConfig())
    assert np.allclose(translations[0], [1.0, 0.5, 0.0], atol=0.06) and scores[0] < 0.05


def _drive_with_strays(root, far: float) -> None:
    """Three scans of a synthetic drive, five static strays ``far`` metres out in each: ``root/seq/00000{0,1,2}.npy``
    (no poses) and the two pairs as ``root/pairs/*.npz`` with their full ground-truth flow, classes and masks."""
    from icpflow.datasets.synthetic import SyntheticDataset

    strays = np.array([[far, far, 0.5], [-far, far, 1.0], [far, -far, 2.0], [0.3 * far, far, 0.0], [far, 0.0, 3.0]])
    drive = SyntheticDataset(split="test", num_sequences=1, frames_per_sequence=3, beams=32, seed=0)
    (root / "seq").mkdir(parents=True)
    (root / "pairs").mkdir()
    for index in range(2):
        pair = drive[index]
        moved = strays @ pair.ego1_from_ego0[:3, :3].T + pair.ego1_from_ego0[:3, 3]  # static: the ego motion only
        pc0 = np.concatenate([pair.pc0, strays]).astype(np.float32)
        pc1 = np.concatenate([pair.pc1, moved]).astype(np.float32)
        padded = {
            name: np.concatenate([getattr(pair, name), np.zeros(len(strays), getattr(pair, name).dtype)])
            for name in ("ground0", "ground1", "dynamic", "classes", "instance")
        }
        flow = np.concatenate([pair.flow, moved - strays]).astype(np.float32)
        np.savez(root / "pairs" / f"{index:06d}.npz", pc0=pc0, pc1=pc1, flow=flow, ego1_from_ego0=pair.ego1_from_ego0,
                 **padded)  # fmt: skip
        np.save(root / "seq" / f"{index:06d}.npy", pc0)
    np.save(root / "seq" / "000002.npy", pc1)


@pytest.mark.slow
def test_stray_returns_far_out_through_label_py_and_eval_py(tiny_student, tmp_path):
    """The entry points over the same strays, 30 km out: ``label.py dataset=sequence`` (the drive's own odometry, its
    ground, the teacher, the shards), ``label.py dataset=pairs`` and ``eval.py`` scoring every point (``crop=null``) of
    the teacher on raw scans, the refining student and its stream. Each completes with every flow finite, in well
    under the memory of one extent-sized grid (6.8 GB at 10 km before)."""
    import json
    import resource

    from icpflow.shards import ShardDataset

    from helpers.labelling import TESTS_ENV

    _drive_with_strays(tmp_path, 30_000.0)
    commands = {
        "sequence": ["label.py", "dataset=sequence", f"dataset.root={tmp_path / 'seq'}", "workers=1"],
        "pairs": ["label.py", "dataset=pairs", f"dataset.root={tmp_path / 'pairs'}", "split=train", "workers=1"],
        "eval": ["eval.py", "dataset=pairs", f"dataset.root={tmp_path / 'pairs'}", f"checkpoint={tiny_student}",
                 "method=[icpflow-raw,student+refine,student-stream+refine]", "crop=null", "limit=1", "bev=1"],
    }  # fmt: skip
    for name, command in commands.items():
        done = subprocess.run(
            [sys.executable, *command, f"out_dir={tmp_path / name}"], cwd=REPO, env=TESTS_ENV, capture_output=True,
            text=True, timeout=600,
        )  # fmt: skip
        assert done.returncode == 0, (name, done.stderr[-1500:])
    assert resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024 < 2000  # MB, the largest of the three
    for name in ("sequence", "pairs"):
        samples = ShardDataset(tmp_path / name)
        assert len(samples) == 2
        for index in range(2):
            sample = samples[index]
            assert len(sample["pc0"]) == len(sample["flow"]) and np.isfinite(sample["flow"]).all(), name
        samples.close()
    rows = json.loads((tmp_path / "eval" / "metrics.json").read_text())["table"]["rows"]
    scored = {row["method"] for row in rows if np.isfinite(row["EPE_overall"])}
    assert scored >= {"icpflow-raw", "student+refine", "student-stream+refine"}, rows[:3]
