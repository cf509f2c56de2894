"""eval.py / icpflow.evaluation: the table equals the metrics module's numbers; shards, failures, bad input."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from icpflow import metrics
from icpflow.baselines import ego_only_flow, zero_flow
from icpflow.datasets.synthetic import SyntheticDataset
from icpflow.evaluation import MetricOptions, evaluate, run_eval
from icpflow.shards.writer import write_index, write_shard

REPO = Path(__file__).resolve().parents[1]
READER = {"split": "val", "num_sequences": 1, "frames_per_sequence": 3, "beams": 32, "azimuth_resolution_deg": 1.0}
SMALL = [f"dataset.reader.{key}={value}" for key, value in READER.items() if key != "split"]


def _cfg(out_dir, *overrides):
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose("eval", [*SMALL, f"out_dir={out_dir}", *overrides])


@pytest.fixture(scope="module")
def dataset():
    return SyntheticDataset(**READER)


def test_eval_reproduces_the_metrics_module(tmp_path, dataset, capsys):
    assert run_eval(_cfg(tmp_path, "bev=1"), progress=False) == 0
    document = json.loads((tmp_path / "metrics.json").read_text())
    assert document["pairs"] == [dataset.sample_id(i) for i in range(len(dataset))]
    for name, predict in (("zero", zero_flow), ("ego", ego_only_flow)):
        paper, three, buckets = metrics.MetricAccumulator(), 0, 0
        for i in range(len(dataset)):
            pair = dataset[i]
            flow = predict(pair)
            paper.add(metrics.frame_pair_stats(pair, flow, crop=32.0))
            args = (pair.pc0, flow, pair.flow, pair.ego1_from_ego0, pair.classes)
            three = three + metrics.av2_bucket_stats(
                *args, ground=pair.ground0, flow_valid=pair.flow_valid, edges=metrics.THREEWAY_EDGES,
                class_to_meta={c: "BACKGROUND" if m == "BACKGROUND" else "FOREGROUND"
                               for c, m in dataset.class_to_meta.items()}, metas=("BACKGROUND", "FOREGROUND"))
            buckets = buckets + metrics.av2_bucket_stats(*args, ground=pair.ground0, flow_valid=pair.flow_valid,
                                                         class_to_meta=dataset.class_to_meta)
        ours = document["methods"][name]
        for weighting, table in paper.table().items():
            for category, row in table.items():
                for column in (*metrics.COLUMNS, "count"):
                    expected, got = row[column], ours["paper"][weighting][category][column]
                    assert (got is None and np.isnan(expected)) or got == pytest.approx(expected, abs=1e-12)
        assert ours["threeway"] == pytest.approx(metrics.threeway_epe(three), abs=1e-12)
        assert ours["bucketed"]["mean"]["dynamic_normalized_epe"] == pytest.approx(
            metrics.bucketed_epe(buckets)["mean"][1], abs=1e-12)
    # ego flow is exact on the static background and scores EPE 1 normalised on movers
    ego = document["methods"]["ego"]
    assert ego["paper"]["point_weighted"]["static_bg"]["EPE"] < 1e-5
    assert ego["bucketed"]["mean"]["dynamic_normalized_epe"] == pytest.approx(1.0, abs=1e-6)
    printed = capsys.readouterr().out
    assert "zero" in printed and "ego" in printed and "dynamic_fg" in printed
    csv_lines = (tmp_path / "metrics.csv").read_text().splitlines()
    assert csv_lines[0].startswith("method,metric,EPE")
    assert any(line.startswith("ego,paper/point_weighted/static_bg,") for line in csv_lines)
    pictures = sorted((tmp_path / "bev").glob("*.png"))
    assert [p.name.rsplit("_", 1)[1] for p in pictures] == ["ego.png", "zero.png"]
    assert all(p.stat().st_size > 10_000 for p in pictures)


class _BrokenAt:
    """A dataset whose pair ``bad`` cannot be read."""

    def __init__(self, inner, bad):
        self.inner, self.bad = inner, bad

    def __len__(self):
        return len(self.inner)

    def sample_id(self, index):
        return self.inner.sample_id(index)

    def pair(self, index, horizon=1):
        if index == self.bad:
            raise OSError("corrupt.bin: truncated file")
        return self.inner.pair(index, horizon)


def test_a_bad_pair_is_recorded_and_skipped_for_every_method(dataset):
    methods = {"zero": lambda pair, index: zero_flow(pair), "ego": lambda pair, index: ego_only_flow(pair)}
    result = evaluate(_BrokenAt(dataset, 0), methods, MetricOptions(class_to_meta=dataset.class_to_meta))
    assert result.pairs == [dataset.sample_id(1)]
    assert result.failures == [{"index": 0, "sample_id": dataset.sample_id(0),
                                "reason": "OSError: corrupt.bin: truncated file"}]
    assert {s["pairs"] for s in result.summaries.values()} == {1}


def test_wrong_flow_shape_is_a_failure_not_a_crash(dataset):
    result = evaluate(dataset, {"bad": lambda pair, index: np.zeros((3, 3), np.float32)}, MetricOptions())
    assert not result.pairs and len(result.failures) == len(dataset)
    assert "shape (3, 3)" in result.failures[0]["reason"]


def _write_labels(out_dir: Path, dataset, flows, shift: float = 0.0) -> None:
    samples = []
    for i, flow in enumerate(flows):
        pair = dataset[i]
        samples.append({"pc0": pair.pc0 + np.float32(shift), "pc1": pair.pc1, "ground0": pair.ground0, "ground1": pair.ground1,
                        "ego1_from_ego0": pair.ego1_from_ego0, "flow": flow,
                        "confidence": np.ones(len(pair.pc0), np.float32),
                        "cluster": np.zeros(len(pair.pc0), np.int32),
                        "attrs": {"sample_id": pair.sample_id, "log_id": pair.log_id, "index": i,
                                  "timestamp0_ns": -1, "timestamp1_ns": -1, "dt": pair.dt}})
    out_dir.mkdir()
    write_shard(out_dir / "shard_00000.h5", samples, "test: true\n", "0" * 16)
    write_index(out_dir / "index.json", {"config_hash": "0" * 16, "shards": [
        {"file": "shard_00000.h5", "samples": [{"sample_id": s["attrs"]["sample_id"], "index": i}
                                               for i, s in enumerate(samples)]}]})


def test_stored_pseudo_labels_are_scored_by_sample_id(tmp_path, dataset):
    perfect = [dataset[i].flow for i in range(len(dataset))]
    _write_labels(tmp_path / "labels", dataset, perfect)
    assert run_eval(_cfg(tmp_path / "eval", "method=shards", f"shards={tmp_path / 'labels'}", "bev=0"),
                    progress=False) == 0
    rows = json.loads((tmp_path / "eval" / "metrics.json").read_text())["methods"]["shards"]["paper"]
    assert rows["point_weighted"]["overall"]["EPE"] == 0.0
    assert rows["point_weighted"]["overall"]["AccS"] == 1.0


def test_stored_labels_of_other_points_are_refused(tmp_path, dataset, capsys):
    _write_labels(tmp_path / "labels", dataset, [dataset[i].flow for i in range(len(dataset))], shift=0.01)
    status = run_eval(_cfg(tmp_path / "eval", "method=shards", f"shards={tmp_path / 'labels'}", "bev=0"),
                      progress=False)
    assert status == 2  # no pair could be scored
    assert "was labelled on other points" in capsys.readouterr().err


@pytest.mark.parametrize("overrides, message", [
    (["method=magic"], "unknown method 'magic'"),
    (["method=student"], "method student needs checkpoint="),
    (["method=shards", "shards=/nonexistent/labels"], "/nonexistent/labels/index.json: no index"),
    (["horizon=5"], "horizon=5 outside 1..2"),
])
def test_bad_requests_get_one_line(tmp_path, capsys, overrides, message):
    assert run_eval(_cfg(tmp_path, *overrides), progress=False) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


def test_eval_script_runs(tmp_path):
    done = subprocess.run([sys.executable, str(REPO / "eval.py"), *SMALL, "limit=1", "bev=0", f"out_dir={tmp_path}",
                           "hydra.run.dir=" + str(tmp_path / "hydra")], capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert "synthetic val: 1 pairs" in done.stdout
    assert (tmp_path / "metrics.json").is_file()
