"""eval.py / icpflow.evaluation: the tables equal the metrics module's numbers (baselines, teacher over several
horizons with and without the tracker, a trained student); one metrics.json schema for one gap or several; each
pair's selection made once; shards, failures, renders, bad input."""

import csv
import json
import subprocess
import sys
from pathlib import Path

import matplotlib.image
import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from fastflow3d.inference.eval_methods import student_method
from icpflow.datasets.from_config import raise_max_horizon
from icpflow.datasets.synthetic.reader import SyntheticDataset
from icpflow.evaluation import MetricOptions, PairScorer, evaluate, method_summary, metrics, read_metrics, run_eval
from icpflow.evaluation.baselines import ego_only_flow, zero_flow
from icpflow.shards.writer import write_index, write_shard

from helpers.data import REPO

STUDENT = {"student": student_method}  # what eval.py adds to the teacher package's methods

READER = {"split": "val", "num_sequences": 1, "frames_per_sequence": 3, "beams": 32, "azimuth_resolution_deg": 1.0}
SMALL = [f"dataset.reader.{key}={value}" for key, value in READER.items() if key != "split"]


def _cfg(out_dir, *overrides):
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose("eval", [*SMALL, f"out_dir={out_dir}", *overrides])


@pytest.fixture(scope="module")
def dataset():
    return SyntheticDataset(**READER)


def expected_summary(dataset, pairs_and_flows) -> dict:
    """What the metrics module says about (pair, full flow) pairs: the paper's table, Threeway EPE, bucketed EPE."""
    paper, three, buckets = metrics.MetricAccumulator(), 0, 0
    threeway_meta = {c: "BACKGROUND" if m == "BACKGROUND" else "FOREGROUND" for c, m in dataset.class_to_meta.items()}
    for pair, flow in pairs_and_flows:
        paper.add(metrics.frame_pair_stats(pair, flow, crop=32.0))
        args = (pair.pc0, flow, pair.flow, pair.ego1_from_ego0, pair.classes)
        three = three + metrics.av2_bucket_stats(
            *args,
            ground=pair.ground0,
            flow_valid=pair.flow_valid,
            edges=metrics.THREEWAY_EDGES,
            class_to_meta=threeway_meta,
            metas=("BACKGROUND", "FOREGROUND"),
        )
        buckets = buckets + metrics.av2_bucket_stats(
            *args, ground=pair.ground0, flow_valid=pair.flow_valid, class_to_meta=dataset.class_to_meta
        )
    return {
        "paper": paper.table(),
        "threeway": metrics.threeway_epe(three),
        "dynamic_normalized_epe": metrics.bucketed_epe(buckets)["mean"][1],
    }


def assert_same_numbers(ours: dict, expected: dict) -> None:
    """A method's summary in metrics.json equals :func:`expected_summary` (NaN written as null)."""
    for weighting, table in expected["paper"].items():
        for category, row in table.items():
            for column in (*metrics.COLUMNS, "count"):
                want, got = row[column], ours["paper"][weighting][category][column]
                assert (got is None and np.isnan(want)) or got == pytest.approx(want, abs=1e-12)
    assert ours["threeway"] == pytest.approx(expected["threeway"], abs=1e-12)
    assert ours["bucketed"]["mean"]["dynamic_normalized_epe"] == pytest.approx(
        expected["dynamic_normalized_epe"], abs=1e-12
    )


def test_eval_reproduces_the_metrics_module(tmp_path, dataset, capsys):
    assert run_eval(_cfg(tmp_path, "bev=1"), progress=False) == 0
    document = json.loads((tmp_path / "metrics.json").read_text())
    assert document["pairs"] == {"1": [dataset.sample_id(i) for i in range(len(dataset))]}
    pairs = [dataset[i] for i in range(len(dataset))]
    for name, predict in (("zero", zero_flow), ("ego", ego_only_flow)):
        assert_same_numbers(document["methods"][name]["1"], expected_summary(dataset, [(p, predict(p)) for p in pairs]))
        # Threeway EPE as published (Chodosh et al. 2023), not through icpflow.evaluation.metrics: over all pairs, the
        # point-weighted EPE of the valid non-ground points with max(|x|, |y|) < 35 m in three groups, foreground
        # (any object class: the synthetic world's classes > 0) moving at >= 0.5 m/s beyond the ego motion,
        # foreground slower, background slower; their mean
        groups = {"foreground_dynamic": [], "foreground_static": [], "background_static": []}
        for pair in pairs:
            flow = predict(pair).astype(np.float64)
            ego = (pair.pc0 @ pair.ego1_from_ego0[:3, :3].T + pair.ego1_from_ego0[:3, 3]) - pair.pc0
            moving = np.linalg.norm(pair.flow - ego, axis=1) / pair.dt >= 0.5
            near = np.abs(pair.pc0[:, :2]).max(axis=1) < 35.0
            valid = np.ones(len(pair.pc0), bool) if pair.flow_valid is None else pair.flow_valid
            kept = valid & ~pair.ground0 & near
            epe = np.linalg.norm(flow - pair.flow, axis=1)
            foreground = pair.classes > 0
            groups["foreground_dynamic"].append(epe[kept & foreground & moving])
            groups["foreground_static"].append(epe[kept & foreground & ~moving])
            groups["background_static"].append(epe[kept & ~foreground & ~moving])
        means = {group: float(np.concatenate(values).mean()) for group, values in groups.items()}
        assert document["methods"][name]["1"]["threeway"] == pytest.approx(
            {**means, "threeway": float(np.mean(list(means.values())))}, rel=1e-6
        )
    # ego flow is exact on the static background and scores EPE 1 normalised on movers
    ego = document["methods"]["ego"]["1"]
    assert ego["paper"]["point_weighted"]["static_bg"]["EPE"] < 1e-5
    assert ego["bucketed"]["mean"]["dynamic_normalized_epe"] == pytest.approx(1.0, abs=1e-6)
    printed = capsys.readouterr().out
    assert "zero" in printed and "ego" in printed and "dynamic_fg" in printed
    csv_lines = (tmp_path / "metrics.csv").read_text().splitlines()
    assert csv_lines[0].startswith("method,horizon,metric,EPE")
    assert any(line.startswith("ego,1,paper/point_weighted/static_bg,") for line in csv_lines)
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
    result = evaluate(_BrokenAt(dataset, 0), {1: methods}, MetricOptions(class_to_meta=dataset.class_to_meta))
    assert result.pairs == {1: [dataset.sample_id(1)]}
    assert result.failures == [
        {"index": 0, "sample_id": dataset.sample_id(0), "horizon": 1, "reason": "OSError: corrupt.bin: truncated file"}
    ]
    assert {s[1]["pairs"] for s in result.summaries.values()} == {1}


def test_wrong_flow_shape_is_a_failure_not_a_crash(dataset):
    result = evaluate(dataset, {1: {"bad": lambda pair, index: np.zeros((3, 3), np.float32)}}, MetricOptions())
    assert result.pairs == {1: []} and len(result.failures) == len(dataset)
    assert "shape (3, 3)" in result.failures[0]["reason"]


def _write_labels(out_dir: Path, dataset, flows, shift: float = 0.0) -> None:
    samples = []
    for i, flow in enumerate(flows):
        pair = dataset[i]
        samples.append(
            {
                "pc0": pair.pc0 + np.float32(shift),
                "pc1": pair.pc1,
                "ground0": pair.ground0,
                "ground1": pair.ground1,
                "ego1_from_ego0": pair.ego1_from_ego0,
                "flow": flow,
                "confidence": np.ones(len(pair.pc0), np.float32),
                "cluster": np.zeros(len(pair.pc0), np.int32),
                "attrs": {
                    "sample_id": pair.sample_id,
                    "log_id": pair.log_id,
                    "index": i,
                    "timestamp0_ns": -1,
                    "timestamp1_ns": -1,
                    "dt": pair.dt,
                },
            }
        )
    out_dir.mkdir()
    write_shard(out_dir / "shard_00000.h5", samples, "test: true\n", "0" * 16)
    write_index(
        out_dir / "index.json",
        {
            "config_hash": "0" * 16,
            "shards": [
                {
                    "file": "shard_00000.h5",
                    "samples": [{"sample_id": s["attrs"]["sample_id"], "index": i} for i, s in enumerate(samples)],
                }
            ],
        },
    )


def test_stored_pseudo_labels_are_scored_by_sample_id(tmp_path, dataset):
    perfect = [dataset[i].flow for i in range(len(dataset))]
    _write_labels(tmp_path / "labels", dataset, perfect)
    assert (
        run_eval(_cfg(tmp_path / "eval", "method=shards", f"shards={tmp_path / 'labels'}", "bev=0"), progress=False)
        == 0
    )
    rows = method_summary(read_metrics(tmp_path / "eval"), "shards")["paper"]
    assert rows["point_weighted"]["overall"]["EPE"] == 0.0
    assert rows["point_weighted"]["overall"]["AccS"] == 1.0


def test_stored_labels_of_other_points_are_refused(tmp_path, dataset, capsys):
    _write_labels(tmp_path / "labels", dataset, [dataset[i].flow for i in range(len(dataset))], shift=0.01)
    status = run_eval(
        _cfg(tmp_path / "eval", "method=shards", f"shards={tmp_path / 'labels'}", "bev=0"), progress=False
    )
    assert status == 2  # no pair could be scored
    assert "was labelled on other points" in capsys.readouterr().err


@pytest.mark.parametrize(
    "overrides, message",
    [
        (["method=magic"], "unknown method 'magic'"),
        (["method=student"], "method student needs checkpoint="),
        (["method=shards", "shards=/nonexistent/labels"], "/nonexistent/labels/index.json: no index"),
        (["method=shards", "shards=/nonexistent/labels", "horizon=[1,2]"], "method shards scores the one horizon"),
        (["horizon=5"], "horizon=5"),  # outside 1..2, or no sample has t + 5 in a 3-scan sequence
        (["horizon=[0,1]"], "horizon must list distinct frame gaps >= 1"),
        (["horizon=one"], "horizon must be an integer, a list or first..last"),
        (["tracker=[true,true]"], "tracker must be true, false or [false,true]"),
        (["limit=0"], "limit must be an integer >= 1, got 0"),
        (["bev=-1"], "bev must be an integer >= 0, got -1"),
        (["render_size=[640]"], "render_size must be [width,height] in pixels"),
        (["weighting=median"], "weighting must be one of point_weighted, per_pair, got 'median'"),
        (["relative_to=gt"], "relative_to must be one of residual, full, got 'gt'"),
        (["crop=-1"], "crop must be a number > 0, got -1"),
        (
            ["method=icpflow", "horizon=3", "dataset.reader.frames_per_sequence=5", "icpflow.pairing.max_frame_gap=2"],
            "icpflow: horizon=3 exceeds the teacher's max_frame_gap 2",
        ),
        # icpflow-raw alone gets the eval's teacher settings too (it ran the defaults, issue 44's ninth session)
        (
            [
                "method=icpflow-raw",
                "horizon=3",
                "dataset.reader.frames_per_sequence=5",
                "icpflow.pairing.max_frame_gap=2",
            ],
            "icpflow: horizon=3 exceeds the teacher's max_frame_gap 2",
        ),
    ],
)
def test_bad_requests_get_one_line(tmp_path, capsys, overrides, message):
    assert run_eval(_cfg(tmp_path, *overrides), progress=False, extra_methods=STUDENT) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


def _structure(value):
    """The shape of a JSON document: dict keys (gap keys as "<k>") and value types, recursively, without numbers."""
    if isinstance(value, dict):
        return {("<k>" if key.isdigit() else key): _structure(v) for key, v in value.items()}
    if isinstance(value, list):
        return [_structure(value[0])] if value else []
    return "number" if isinstance(value, (int, float)) or value is None else type(value).__name__


def test_one_gap_and_several_gaps_write_one_schema(tmp_path):
    one, several = tmp_path / "one", tmp_path / "several"
    assert run_eval(_cfg(one, "limit=1", "bev=0"), progress=False) == 0
    assert run_eval(_cfg(several, "limit=1", "bev=0", "horizon=1..2"), progress=False) == 0
    first, second = read_metrics(one), read_metrics(several)
    config = ("config", "settings")  # the settings hold the gaps asked for, the config every option given
    assert _structure({k: v for k, v in first.items() if k not in config}) == _structure(
        {k: v for k, v in second.items() if k not in config}
    )
    assert first["horizons"] == [1] and second["horizons"] == [1, 2] and first["complete"] and second["complete"]
    assert [(r["method"], r["horizon"]) for r in second["table"]["rows"]] == [
        (m, k) for m in ("zero", "ego") for k in (1, 2)
    ]
    # the start scan of sample 0 is the same in both runs: the same numbers at gap 1
    assert first["pairs"]["1"] == second["pairs"]["1"]
    for name in ("zero", "ego"):
        ours, theirs = method_summary(first, name, 1), method_summary(second, name, 1)
        assert {k: v for k, v in ours.items() if k != "seconds_per_pair"} == {
            k: v for k, v in theirs.items() if k != "seconds_per_pair"
        }
    header = (one / "metrics.csv").read_text().splitlines()[0]
    assert header == (several / "metrics.csv").read_text().splitlines()[0]


def test_each_pair_is_selected_once_for_every_method_and_gap(dataset, monkeypatch):
    built = []
    original = metrics.PairTruth.__init__

    def counting(self, *args, **kwargs):
        built.append(len(args[0]))
        original(self, *args, **kwargs)

    monkeypatch.setattr(metrics.PairTruth, "__init__", counting)
    zero, ego = (lambda pair, index: zero_flow(pair)), (lambda pair, index: ego_only_flow(pair))
    options = MetricOptions(class_to_meta=dataset.class_to_meta)
    result = evaluate(dataset, {1: {"zero": zero, "ego": ego, "again": ego}}, options)
    assert len(built) == len(dataset) == len(result.pairs[1])  # once per pair, not per method or statistic
    # and the shared selection gives each method the metrics module's own numbers
    pair = dataset[0]
    scorer = PairScorer(pair, options)
    for predict in (zero_flow, ego_only_flow):
        scores = scorer.score(predict(pair), 0.0)
        expected = metrics.frame_pair_stats(pair, predict(pair))
        for category, sums in expected.items():
            np.testing.assert_array_equal(scores.paper[category], sums)
        args = (pair.pc0, predict(pair), pair.flow, pair.ego1_from_ego0, pair.classes)
        buckets = metrics.av2_bucket_stats(
            *args, ground=pair.ground0, flow_valid=pair.flow_valid, class_to_meta=dataset.class_to_meta
        )
        np.testing.assert_array_equal(scores.buckets, buckets)


def test_every_hook_sees_every_method_on_every_scored_pair(dataset):
    seen = []
    zero, ego = (lambda pair, index: zero_flow(pair)), (lambda pair, index: ego_only_flow(pair))
    evaluate(_BrokenAt(dataset, 0), {1: {"zero": zero, "ego": ego}}, MetricOptions(), hooks=[seen.append])
    assert [(p.position, p.horizon, p.index, sorted(p.flows)) for p in seen] == [(0, 1, 1, ["ego", "zero"])]
    np.testing.assert_array_equal(seen[0].flows["ego"], ego_only_flow(dataset[1]))


def test_readers_taking_max_horizon_get_the_largest_horizon():
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        cfg = compose("eval", ["dataset=sequence", "dataset.root=/data"])  # ScanSequenceDataset(max_horizon=...)
        pca = compose("eval", ["dataset=waymo", "dataset.root=/data"])  # max_horizon fixed by its files
    assert cfg.dataset.reader.max_horizon == 1
    assert raise_max_horizon(cfg, 3) and cfg.dataset.reader.max_horizon == 3
    assert not raise_max_horizon(cfg, 2) and cfg.dataset.reader.max_horizon == 3  # a larger one is kept
    assert not raise_max_horizon(pca, 3) and "max_horizon" not in pca.dataset.reader


def test_long_horizon_table_reproduces_the_metrics_module(tmp_path, capsys):
    from icpflow.teacher import ICPFlow
    from icpflow.teacher.config import teacher_config
    from icpflow.teacher.long_horizon import sample_tracker_flow

    cfg = _cfg(tmp_path, "method=[zero,icpflow]", "horizon=1..2", "tracker=[false,true]", "bev=1")
    assert run_eval(cfg, progress=False) == 0
    document = json.loads((tmp_path / "metrics.json").read_text())
    dataset = instantiate(document["config"]["dataset"]["reader"])  # the reader as the run opened it
    pairs = {k: dataset.pair(0, horizon=k) for k in (1, 2)}
    assert document["horizons"] == [1, 2]
    assert document["pairs"] == {str(k): [pairs[k].sample_id] for k in (1, 2)}
    assert pairs[1].timestamp0_ns == pairs[2].timestamp0_ns  # the same start scan at both horizons
    teacher = ICPFlow(teacher_config(cfg))
    direct = {
        k: teacher(
            p.pc0, p.pc1, ego1_from_ego0=p.ego1_from_ego0, ground0=p.ground0, ground1=p.ground1, gap=k, dt=p.dt
        ).flow
        for k, p in pairs.items()
    }
    flows = {
        "zero": {k: zero_flow(p) for k, p in pairs.items()},
        "icpflow": direct,
        "icpflow+tracker": {1: direct[1], 2: sample_tracker_flow(teacher, dataset, 0, 2, pairs[2]).flow},
    }
    rows = document["table"]["rows"]
    assert [(row["method"], row["horizon"]) for row in rows] == [(m, k) for m in flows for k in (1, 2)]
    for row in rows:
        name, k = row["method"], row["horizon"]
        expected = expected_summary(dataset, [(pairs[k], flows[name][k])])
        assert_same_numbers(document["methods"][name][str(k)], expected)
        assert row["dt_s"] == pytest.approx(pairs[k].dt) and pairs[k].dt == pytest.approx(0.1 * k, abs=1e-3)
        for category in metrics.CATEGORIES:
            assert row[f"EPE_{category}"] == pytest.approx(
                expected["paper"]["point_weighted"][category]["EPE"], abs=1e-12
            )
    by_key = {(row["method"], row["horizon"]): row for row in rows}
    assert by_key["icpflow", 2]["EPE_overall"] != by_key["icpflow+tracker", 2]["EPE_overall"]  # the tracker ran
    with open(tmp_path / "metrics.csv", newline="") as handle:
        table = [r for r in csv.DictReader(handle) if r["metric"] == "paper/point_weighted/dynamic_fg"]
    assert [(r["method"], int(r["horizon"]), float(r["EPE"])) for r in table] == [
        (row["method"], row["horizon"], pytest.approx(row["EPE_dynamic_fg"], rel=1e-12)) for row in rows
    ]
    printed = capsys.readouterr().out
    assert "horizons 1, 2" in printed and printed.count("icpflow+tracker") == 2
    assert sorted(p.relative_to(tmp_path / "bev").as_posix() for p in (tmp_path / "bev").rglob("*.png")) == sorted(
        f"k{k}/{pairs[k].sample_id.replace('/', '_')}_{name}.png" for k in (1, 2) for name in flows
    )


def test_student_row_reproduces_the_metrics_module(tiny_student, tmp_path, dataset):
    from fastflow3d.inference.predictor import Predictor

    assert (
        run_eval(
            _cfg(tmp_path / "eval", "method=[ego,student]", f"checkpoint={tiny_student}", "bev=0"),
            progress=False,
            extra_methods=STUDENT,
        )
        == 0
    )
    document = json.loads((tmp_path / "eval" / "metrics.json").read_text())
    predictor = Predictor.load(tiny_student)
    pairs = [dataset[i] for i in range(len(dataset))]
    flows = [predictor(p.pc0, p.pc1, p.ego1_from_ego0) for p in pairs]
    assert_same_numbers(method_summary(document, "student"), expected_summary(dataset, list(zip(pairs, flows))))
    # what the student ran (precision auto: float32 for a model without an int8 network) is said under the table
    assert document["method_descriptions"] == {"student": f"f32 network, {predictor.backend}"}
    # the network moves points off the ego flow: its row is not the ego baseline's
    overall = {
        name: method_summary(document, name)["paper"]["point_weighted"]["overall"]["EPE"] for name in ("ego", "student")
    }
    assert overall["student"] != pytest.approx(overall["ego"], abs=1e-6)


def test_render_writes_one_picture_per_method(tmp_path, dataset):
    from icpflow.viz.pictures import offscreen_problem

    problem = offscreen_problem()
    if problem:
        pytest.skip(problem)
    assert (
        run_eval(
            _cfg(tmp_path, "method=[zero,ego]", "limit=1", "bev=0", "render=1", "render_size=[160,120]"), progress=False
        )
        == 0
    )
    stem = dataset.sample_id(0).replace("/", "_")
    pictures = sorted((tmp_path / "render").glob("*.png"))
    assert [p.name for p in pictures] == [f"{stem}_ego.png", f"{stem}_zero.png"]
    assert all(matplotlib.image.imread(p).shape[:2] == (120, 160) for p in pictures)
    assert not (tmp_path / "bev").exists()


def test_eval_script_runs(tmp_path):
    done = subprocess.run(
        [
            sys.executable,
            str(REPO / "eval.py"),
            *SMALL,
            "limit=1",
            "bev=0",
            f"out_dir={tmp_path}",
            "hydra.run.dir=" + str(tmp_path / "hydra"),
        ],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr
    assert "synthetic val: 1 pairs" in done.stdout
    assert (tmp_path / "metrics.json").is_file()


@pytest.mark.parametrize("value, expected", [("null", None), ("auto", "auto"), ("1.73", 1.73)])
def test_the_students_height_frame_is_an_eval_option(tiny_student, tmp_path, dataset, value, expected):
    """eval.py sensor_height=... reaches the student's Predictor (the advice its height-frame warning gives)."""
    method = student_method(_cfg(tmp_path / "eval", f"checkpoint={tiny_student}", f"sensor_height={value}"))
    assert method.predictor.sensor_height == expected
