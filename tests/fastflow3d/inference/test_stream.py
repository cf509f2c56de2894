"""The streaming Predictor (fastflow3d.inference.stream.FlowStream; its odometry, icpflow.scans.odometry, is
tests/icpflow/scans/test_odometry.py): the flow of a stream is the Predictor's with the stream's ego motion and masks;
the ego motion is exact on the synthetic world; every bad stream (a gap, a skipped scan, time going backwards, too few
points, a lost
track, another frame) is one warning and never a silent wrong flow, and the other frames keep theirs."""

import json
import os
import re
import threading
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from fastflow3d.inference.predictor import Predictor
from fastflow3d.inference.stream import FlowStream, StreamWarning, overlap_threads
from icpflow.core.geometry import invert
from icpflow.core.threads import available_cores
from icpflow.datasets.synthetic.reader import SyntheticDataset

from helpers.disk import fail_fsync_after
from helpers.drives import corridor, synthetic_drive


@pytest.fixture(scope="module")
def moving():
    """A sequence of 8 frames whose ego drives (seed 3: about 8 m/s)."""
    pairs, scans = synthetic_drive(3, 8)
    assert np.linalg.norm(pairs[0].ego1_from_ego0[:3, 3]) > 0.3
    return pairs, scans


@pytest.fixture(scope="module")
def other_place():
    return synthetic_drive(11, 4)


def _errors(truth, estimate):
    delta = invert(truth) @ estimate
    angle = np.degrees(np.arccos(np.clip((np.trace(delta[:3, :3]) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(delta[:3, 3])), float(angle)


def test_the_stream_gives_the_predictors_flow_with_its_own_ego_motion(tiny_student, moving):
    pairs, scans = moving
    stream = FlowStream(Predictor.load(tiny_student))
    first = stream.push(scans[0], timestamp=0.0, source="s0")
    assert first.prediction is None and np.array_equal(first.pose, np.eye(4))
    predictor = Predictor.load(tiny_student)
    for k, pair in enumerate(pairs[:4], start=1):
        step = stream.push(scans[k], timestamp=0.1 * k, source=f"s{k}")
        assert (step.source, step.previous, step.restarted) == (f"s{k}", f"s{k - 1}", False)
        ego = step.prediction.ego1_from_ego0
        expected = predictor.predict(pair.pc0, pair.pc1, ego, step.prediction.ground0, None)
        np.testing.assert_allclose(step.prediction.flow, expected.flow, atol=1e-5)
        assert _errors(pair.ego1_from_ego0, ego)[0] < 0.02 and step.prediction.ego_estimated
    # the trajectory: the product of the steps, in the first scan's frame
    truth = np.eye(4)
    for pair in pairs[:4]:
        truth = truth @ invert(pair.ego1_from_ego0)
    assert np.linalg.norm(step.pose[:3, 3] - truth[:3, 3]) < 4 * 0.02  # four steps of at most 2 cm


def _pushed(stream, scans, times=None, sources=None):
    """Push every scan; returns the steps and the StreamWarning messages."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        steps = [
            stream.push(scan, None if times is None else times[k], None if sources is None else sources[k])
            for k, scan in enumerate(scans)
        ]
    return steps, [str(w.message) for w in caught if issubclass(w.category, StreamWarning)]


@pytest.mark.parametrize("kind", ["gap", "backwards"])
def test_a_time_gap_or_time_going_backwards_restarts_the_odometry(tiny_student, moving, kind):
    pairs, scans = moving
    times = [0.0, 0.1, 0.2, 0.9, 1.0] if kind == "gap" else [0.0, 0.1, 0.2, 0.15, 0.25]
    steps, said = _pushed(FlowStream(Predictor.load(tiny_student)), scans[:5], times, [f"s{k}" for k in range(5)])
    words = "s after the previous scan" if kind == "gap" else "does not follow"
    assert len(said) == 1 and said[0].startswith("FlowStream: s3: ") and words in said[0], said
    assert [step.restarted for step in steps[1:]] == [False, False, True, False]
    for pair, step in zip(pairs, steps[1:]):  # every pair keeps its flow, the one across the gap included
        assert step.prediction is not None and _errors(pair.ego1_from_ego0, step.prediction.ego1_from_ego0)[0] < 0.03


def test_a_skipped_scan_is_bridged_by_the_next_pair(tiny_student, moving):
    pairs, scans = moving
    stream = FlowStream(Predictor.load(tiny_student))
    stream.push(scans[0], source="s0")
    stream.push(scans[1], source="s1")
    with pytest.warns(StreamWarning, match=r"^FlowStream: s2: skipped \(unreadable\); the next pair spans the gap"):
        stream.skip("s2", "unreadable")
    step = stream.push(scans[3], source="s3")
    truth = pairs[2].ego1_from_ego0 @ pairs[1].ego1_from_ego0  # s1 -> s3
    assert step.previous == "s1" and step.restarted and _errors(truth, step.prediction.ego1_from_ego0)[0] < 0.03


def test_a_scan_with_too_few_points_gets_ego_only_flow_and_a_warning(tiny_student, moving):
    _, scans = moving
    stream = FlowStream(Predictor.load(tiny_student))
    stream.push(scans[0])
    steps, said = _pushed(stream, [scans[1][:50], scans[2], scans[3]], sources=["few", "s2", "s3"])
    assert len(said) == 1 and said[0].startswith("FlowStream: few: 50 points, too few"), said
    for step in steps[:2]:  # both pairs of the scan: the identity, ego flow only
        assert step.prediction.ego_assumed and np.array_equal(step.prediction.ego1_from_ego0, np.eye(4))
        assert not step.prediction.in_grid.any() and not step.prediction.flow.any()
    assert steps[2].restarted and steps[2].prediction.ego_estimated  # then a new track


def test_a_step_whose_surfaces_leave_a_direction_unfixed_is_said(tiny_student):
    """A drive down a corridor (two parallel walls): each pair's ego motion comes with one line saying that the walls
    do not fix it along one direction."""
    scans = [corridor(k, shift=0.8 * k) for k in range(3)]
    steps, said = _pushed(FlowStream(Predictor.load(tiny_student)), scans, sources=["c0", "c1", "c2"])
    assert [line.split(":")[1].strip() for line in said] == ["c1", "c2"], said
    assert all("do not fix the ego motion along one direction" in line for line in said)
    assert steps[1].prediction is not None


def test_splicing_two_places_is_a_lost_track_without_flow(tiny_student, moving, other_place):
    """Two unrelated sequences one after the other: the pair across the splice gets no flow and one warning; the
    odometry starts again on the second place and its pairs keep exact ego motion."""
    pairs, scans = moving
    others, other_scans = other_place
    spliced = [*scans[:4], *other_scans[:4]]
    steps, said = _pushed(FlowStream(Predictor.load(tiny_student)), spliced, sources=[f"s{k}" for k in range(8)])
    assert len(said) == 1 and said[0].startswith("FlowStream: s4: lost track"), said
    assert steps[4].prediction is None and steps[4].restarted
    for k, pair in ((1, pairs[0]), (2, pairs[1]), (3, pairs[2]), (5, others[0]), (6, others[1]), (7, others[2])):
        assert steps[k].prediction is not None, k
        assert _errors(pair.ego1_from_ego0, steps[k].prediction.ego1_from_ego0)[0] < 0.03, k


@pytest.mark.parametrize("depth", [1, 2])
def test_an_overlapped_stream_gives_the_same_steps_depth_pushes_late(tiny_student, moving, other_place, depth):
    """overlap=True (the network of a pair beside the next scan's steps, in a worker thread): the very steps of the
    plain stream, in order, each ``depth`` pushes late and the last ones from flush() (until it gives None), through
    a scan of too few points, a skipped scan and a lost track, with the refinement on."""
    _, scans = moving
    _, other_scans = other_place
    scans = [scans[0], scans[1], scans[2][:50], *scans[3:6], *other_scans[:3]]
    sources = [f"s{k}" for k in range(len(scans))]

    def run(overlap):
        stream = FlowStream(Predictor.load(tiny_student, refine=True), overlap=overlap, depth=depth)
        steps = []
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            for k, (scan, source) in enumerate(zip(scans, sources)):
                if k == 5:
                    stream.skip("gone", "unreadable")
                steps.append(stream.push(scan, source=source))
            steps.extend(iter(stream.flush, None))
            steps.append(stream.flush())  # nothing left
        said = [str(w.message) for w in caught if issubclass(w.category, StreamWarning)]
        return steps, said

    plain, plain_said = run(False)
    overlapped, overlapped_said = run(True)
    # plain: flush has nothing; overlapped: nothing for the first depth pushes, every step after them
    assert plain[-1] is None and overlapped[:depth] == [None] * depth and overlapped[-1] is None
    assert len(overlapped) == len(plain) + depth
    assert overlapped_said == plain_said and len(plain_said) == 3, plain_said  # too few, skipped, lost track
    for expected, step in zip(plain[:-1], overlapped[depth:-1], strict=True):
        assert (step.source, step.previous, step.restarted, step.fitness) == (
            expected.source,
            expected.previous,
            expected.restarted,
            expected.fitness,
        )
        assert (step.pose is None) == (expected.pose is None) and (step.prediction is None) == (
            expected.prediction is None
        )
        # the odometry's threaded reductions (KISS-ICP) may round differently from run to run: 1e-16 m on a pose
        if step.pose is not None:
            np.testing.assert_allclose(step.pose, expected.pose, atol=1e-9)
        if step.prediction is not None:
            for name in ("in_grid", "ground0", "refined"):
                np.testing.assert_array_equal(getattr(step.prediction, name), getattr(expected.prediction, name))
            for name in ("flow", "residual", "ego1_from_ego0"):
                np.testing.assert_allclose(
                    getattr(step.prediction, name), getattr(expected.prediction, name), atol=1e-5
                )
    assert sum(step.prediction is not None for step in plain[:-1]) >= 5
    with pytest.raises(ValueError, match="depth must be at least 1, got 0"):
        FlowStream(Predictor.load(tiny_student), overlap=True, depth=0)


def test_a_scan_from_another_frame_is_caught_by_the_height_check(tiny_student, moving):
    """Scans that suddenly come 1.5 m lower (another sensor's origin): the height check says so, lifts them by their
    own ground, and the pairs keep the right ego motion."""
    pairs, scans = moving
    lowered = [scan if k < 4 else scan - np.array([0, 0, 1.5], np.float32) for k, scan in enumerate(scans)]
    stream = FlowStream(Predictor.load(tiny_student), check_every=1)
    steps, said = _pushed(stream, lowered, sources=[f"s{k}" for k in range(len(lowered))])
    assert len(said) == 1 and re.match(r"FlowStream: s4: the ground moved by \+1\.[45]\d m", said[0]), said
    for pair, step in zip(pairs[4:], steps[5:]):
        assert _errors(pair.ego1_from_ego0, step.prediction.ego1_from_ego0)[0] < 0.03


def test_infer_streams_a_folder_and_bridges_a_broken_scan(tiny_student, moving, tmp_path, capsys):
    """fastflow3d-infer MODEL DIR --out OUT: one .npz per consecutive pair, named after its first scan, holding what
    a pair's output holds; a broken scan mid-stream is one warning naming it and the next pair spans the gap; the
    recording holds the pairs and the trajectory."""
    pytest.importorskip("rerun", reason="rerun-sdk is an optional dependency (pip install 'icpflow[viz]')")
    from fastflow3d.inference.cli import main as infer_main

    from helpers.rerun import read_recording

    pairs, scans = moving
    folder, out, recording = tmp_path / "scans", tmp_path / "flows", tmp_path / "stream.rrd"
    folder.mkdir()
    for k, scan in enumerate(scans[:5]):
        np.save(folder / f"{k:06d}.npy", scan)
    (folder / "000002.npy").write_bytes(b"not a scan")
    assert infer_main([str(tiny_student), str(folder), "--out", str(out), "--rerun", str(recording)]) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("infer: warning")]
    assert len(err) == 1 and "000002.npy: skipped" in err[0] and "the next pair spans the gap" in err[0], err
    outputs = ["000000.npz", "000001.npz", "000003.npz"]
    assert sorted(path.name for path in out.iterdir()) == [*outputs, "stream.json"]
    manifest = json.loads((out / "stream.json").read_text())
    assert manifest["complete"] and manifest["outputs"] == outputs and len(manifest["scans"]) == 5
    assert [entry["scans"] for entry in manifest["failed"]] == [[None, str(folder / "000002.npy")]]
    with np.load(out / "000001.npz") as bridged:  # 000001 -> 000003
        truth = pairs[2].ego1_from_ego0 @ pairs[1].ego1_from_ego0
        assert _errors(truth, bridged["ego1_from_ego0"])[0] < 0.03 and bool(bridged["ego_estimated"])
        assert {"flow", "residual", "in_grid", "ground0", "ego_assumed"} <= set(bridged.files)
        assert bridged["flow"].shape == scans[1].shape
    entities = read_recording(recording)
    assert {"pc0", "pc1", "flow/fastflow3d/moved", "trajectory"} <= set(entities)
    assert len(entities["pc0"]) == 3


def test_a_disk_filling_up_mid_stream_is_one_line_and_keeps_the_flows_written(
    tiny_student, moving, tmp_path, monkeypatch, capsys
):
    """A full disk at the second flow file of a stream is one line naming that file, exit status 2; the first flow
    stays whole, nothing is half-written, the manifest does not call the run complete, and the same command once
    there is space replaces its own outputs."""
    from fastflow3d.inference.cli import main as infer_main

    _, scans = moving
    folder, out = tmp_path / "scans", tmp_path / "flows"
    folder.mkdir()
    for k, scan in enumerate(scans[:5]):
        np.save(folder / f"{k:06d}.npy", scan)
    fail_fsync_after(monkeypatch, 4, place=out)  # the manifest's claim and the first flow (file and folder each)
    assert infer_main([str(tiny_student), str(folder), "--out", str(out)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert (
        err[-1]
        == f"infer: {out / '000001.npz'}: cannot write (No space left on device); free space there or write elsewhere"
    )
    assert not [line for line in err[:-1] if "cannot write" in line or "Traceback" in line], err
    assert sorted(path.name for path in out.iterdir()) == ["000000.npz", "stream.json"]
    with np.load(out / "000000.npz") as first:
        assert first["flow"].shape == scans[0].shape
    assert not json.loads((out / "stream.json").read_text())["complete"]  # the disk took no update of it either
    monkeypatch.undo()  # space is freed: the same command replaces its own outputs
    assert infer_main([str(tiny_student), str(folder), "--out", str(out)]) == 0
    assert json.loads((out / "stream.json").read_text())["outputs"] == [f"{k:06d}.npz" for k in range(4)]


def test_a_rerun_removes_only_the_names_its_stream_writes(tiny_student, moving, tmp_path, capsys):
    """Outputs are claimed by name: a rerun of the same stream replaces the flow files its scans name and nothing
    else. A file of the user's there (even a ``.npz``), or a folder or link under one of the stream's names, refuses
    the rerun in one line before anything is removed."""
    from fastflow3d.inference.cli import main as infer_main

    _, scans = moving
    folder, out = tmp_path / "scans", tmp_path / "flows"
    folder.mkdir()
    for k, scan in enumerate(scans[:3]):
        np.save(folder / f"{k:06d}.npy", scan)
    assert infer_main([str(tiny_student), str(folder), "--out", str(out)]) == 0
    flows = {name: (out / name).read_bytes() for name in ("000000.npz", "000001.npz")}
    for name, make in (
        ("my_results.npz", lambda path: np.savez(path, mine=np.ones(3))),
        ("notes.txt", lambda path: path.write_text("mine")),
        ("000002.npz", lambda path: path.write_text("mine")),  # the last scan starts no pair: not a stream's name
    ):
        make(out / name)
        assert infer_main([str(tiny_student), str(folder), "--out", str(out)]) == 2
        assert f"{out}: holds {name}, not an output of this stream" in capsys.readouterr().err
        assert (out / name).exists() and all((out / k).read_bytes() == v for k, v in flows.items())
        (out / name).unlink()
    (out / "000001.npz").unlink()
    (out / "000001.npz").mkdir()  # a folder under a name the stream writes
    assert infer_main([str(tiny_student), str(folder), "--out", str(out)]) == 2
    assert "000001.npz is not a regular file" in capsys.readouterr().err
    assert (out / "000000.npz").read_bytes() == flows["000000.npz"]  # nothing removed before the refusal
    (out / "000001.npz").rmdir()
    (out / "000001.npz").symlink_to(folder / "000000.npy")
    assert infer_main([str(tiny_student), str(folder), "--out", str(out)]) == 2
    assert "000001.npz is not a regular file" in capsys.readouterr().err and (folder / "000000.npy").is_file()


def test_a_pair_that_cannot_be_computed_is_skipped_listed_and_the_stream_goes_on(
    tiny_student, moving, tmp_path, monkeypatch, capsys
):
    """Out of memory in one pair's network and in another scan's ground (a scan far too large would do it): each pair
    gets no flow, one warning naming its scan, and a line in the manifest with the reason; every other pair keeps
    its flow (the one across the failed scan spans it), exit status 0, and the last line counts the failures."""
    from fastflow3d.inference.cli import main as infer_main
    from fastflow3d.inference.predictor import Predictor

    _, scans = moving
    folder, out = tmp_path / "scans", tmp_path / "flows"
    folder.mkdir()
    for k, scan in enumerate(scans[:7]):
        np.save(folder / f"{k:06d}.npy", scan)
    residual, masks, calls = Predictor.pair_residual, Predictor.scan_masks, []

    def second_pair_fails(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 2:  # the pair 000001 -> 000002
            raise MemoryError("Unable to allocate 9.31 GiB for an array")
        return residual(self, *args, **kwargs)

    def fifth_scan_fails(self, name, points, given):
        if len(points) == len(scans[4]) and np.array_equal(points[:, :2], scans[4][:, :2]):
            raise MemoryError()
        return masks(self, name, points, given)

    monkeypatch.setattr(Predictor, "pair_residual", second_pair_fails)
    monkeypatch.setattr(Predictor, "scan_masks", fifth_scan_fails)
    assert infer_main([str(tiny_student), str(folder), "--out", str(out)]) == 0
    said = capsys.readouterr()
    err = said.err.splitlines()
    warned = sorted(line for line in err if "could not be computed" in line)  # said as each pair comes out
    assert len(warned) == 2 and "000002.npy" in warned[0] and "Unable to allocate 9.31 GiB" in warned[0], err
    assert "000004.npy" in warned[1] and "(MemoryError)" in warned[1], err
    assert not [line for line in err if "Traceback" in line or "unexpected" in line], err
    outputs = ["000000.npz", "000002.npz", "000003.npz", "000005.npz"]  # 000003 -> 000005 spans the failed scan
    assert sorted(path.name for path in out.glob("*.npz")) == outputs
    manifest = json.loads((out / "stream.json").read_text())
    assert manifest["complete"] and manifest["outputs"] == outputs
    names = [str(folder / f"{k:06d}.npy") for k in range(7)]
    assert manifest["failed"] == [
        {"scans": names[1:3], "reason": "Unable to allocate 9.31 GiB for an array"},
        {"scans": names[3:5], "reason": "MemoryError"},
    ]
    assert said.out.strip().endswith(f"network; 2 failed, listed in {out / 'stream.json'})"), said.out


def test_a_stopped_stream_lists_the_flows_it_kept(tiny_student, moving, tmp_path, monkeypatch):
    """Ctrl-C (``Stop``) at the sixth scan of seven: exit 130, the manifest not complete and listing the flows kept
    (those written before the stop); the same command afterwards replaces them."""
    from fastflow3d.inference import stream as stream_module
    from fastflow3d.inference.cli import main as infer_main
    from icpflow.core.errors_and_signals import Stop

    _, scans = moving
    folder, out = tmp_path / "scans", tmp_path / "flows"
    folder.mkdir()
    for k, scan in enumerate(scans[:7]):
        np.save(folder / f"{k:06d}.npy", scan)
    push, pushed = stream_module.FlowStream.push, []

    def stopping(self, points, *args, **kwargs):
        pushed.append(1)
        if len(pushed) == 6:  # the stream runs its pairs behind the scans it reads: some are out by then
            raise Stop(2)
        return push(self, points, *args, **kwargs)

    monkeypatch.setattr(stream_module.FlowStream, "push", stopping)
    assert infer_main([str(tiny_student), str(folder), "--out", str(out)]) == 130
    manifest = json.loads((out / "stream.json").read_text())
    kept = sorted(path.name for path in out.glob("*.npz"))
    assert not manifest["complete"] and manifest["outputs"] == kept and len(kept) >= 1
    monkeypatch.undo()
    assert infer_main([str(tiny_student), str(folder), "--out", str(out)]) == 0
    assert json.loads((out / "stream.json").read_text())["outputs"] == [f"{k:06d}.npz" for k in range(6)]


def test_infer_stream_needs_a_folder_or_glob_of_two_scans(tiny_student, tmp_path, capsys):
    from fastflow3d.inference.cli import main as infer_main

    (tmp_path / "one").mkdir()
    np.save(tmp_path / "one" / "a.npy", np.zeros((200, 3), np.float32))
    assert infer_main([str(tiny_student), str(tmp_path / "one")]) == 2
    assert "a stream needs at least two scans" in capsys.readouterr().err
    assert infer_main([str(tiny_student), str(tmp_path / "one"), "--ego", "x.txt"]) == 2
    assert "--poses / --ego give a pair's ego motion" in capsys.readouterr().err


def test_infer_stream_reads_natural_order_and_refuses_two_scans_of_one_stem(tiny_student, moving, tmp_path, capsys):
    """1, 2, 10 (not 1, 10, 2: every flow between the wrong scans) as dataset=sequence reads them; 1.bin beside
    1.npy, or one name in two folders of a glob, would write one output for two pairs: refused, nothing written."""
    from fastflow3d.inference.cli import main as infer_main

    _, scans = moving
    folder, out = tmp_path / "scans", tmp_path / "out"
    folder.mkdir()
    for name, scan in zip(("1", "2", "10"), scans):
        np.save(folder / f"{name}.npy", scan)
    assert infer_main([str(tiny_student), str(folder), "--out", str(out)]) == 0
    manifest = json.loads((out / "stream.json").read_text())
    assert [Path(name).name for name in manifest["scans"]] == ["1.npy", "2.npy", "10.npy"]
    assert manifest["outputs"] == ["1.npz", "2.npz"]
    with np.load(out / "2.npz") as flow:  # scan 2 -> scan 10 is the stream's second step
        assert flow["flow"].shape == scans[1].shape
    scans[0].astype(np.float32).tofile(folder / "1.bin")
    assert infer_main([str(tiny_student), str(folder), "--out", str(tmp_path / "other")]) == 2
    assert "two scans named '1'" in capsys.readouterr().err and not (tmp_path / "other").exists()
    (folder / "1.bin").unlink()
    second = tmp_path / "second"
    second.mkdir()
    np.save(second / "2.npy", scans[2])
    glob = str(tmp_path / "*" / "*.npy")
    assert infer_main([str(tiny_student), glob, "--out", str(tmp_path / "other")]) == 2
    assert "two scans named '2'" in capsys.readouterr().err


def test_infer_outputs_never_replace_inputs_nor_mix_runs(tiny_student, moving, tmp_path, capsys):
    """An OUT that holds the input scans (.npz scans would become flows), a pair's output or picture that is an
    input scan, another run's OUT or a folder of other files: each refused in one line, inputs untouched. A rerun of
    the same stream replaces its own outputs (said); a stream without a single flow is an error, not '0 flows'."""
    from fastflow3d.inference.cli import main as infer_main

    _, scans = moving
    folder = tmp_path / "scans"
    folder.mkdir()
    for k, scan in enumerate(scans[:3]):
        np.savez(folder / f"{k}.npz", points=scan)
    before = {path.name: path.read_bytes() for path in folder.iterdir()}
    assert infer_main([str(tiny_student), str(folder), "--out", str(folder)]) == 2
    assert "holds the input scans" in capsys.readouterr().err
    s0, s1 = folder / "0.npz", folder / "1.npz"
    for option in (["--out", str(s0)], ["--out", str(tmp_path / "f.npz"), "--bev", str(s1)]):
        assert infer_main([str(tiny_student), str(s0), str(s1), *option]) == 2
        assert "is an input of this run" in capsys.readouterr().err
    assert {path.name: path.read_bytes() for path in folder.iterdir()} == before
    out = tmp_path / "out"
    assert infer_main([str(tiny_student), str(folder), "--out", str(out)]) == 0
    capsys.readouterr()
    assert infer_main([str(tiny_student), str(folder), "--out", str(out)]) == 0  # the same stream again
    assert "a rerun of the same stream; its 2 earlier output(s) are replaced" in capsys.readouterr().err
    assert sorted(path.name for path in out.iterdir()) == ["0.npz", "1.npz", "stream.json"]
    (folder / "2.npz").unlink()  # another stream (two scans) into the same OUT
    assert infer_main([str(tiny_student), str(folder), "--out", str(out)]) == 2
    assert "holds another stream's flows" in capsys.readouterr().err
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "notes.txt").write_text("mine")
    assert infer_main([str(tiny_student), str(folder), "--out", str(tmp_path / "used")]) == 2
    assert "holds 1 file(s) of no stream of ours" in capsys.readouterr().err
    assert (tmp_path / "used" / "notes.txt").read_text() == "mine"
    broken = tmp_path / "broken"
    broken.mkdir()
    for name in ("a.npy", "b.npy"):
        (broken / name).write_bytes(b"not a scan")
    assert infer_main([str(tiny_student), str(broken), "--out", str(tmp_path / "none")]) == 2
    assert "no flow: the stream gave none of its 2 scans a pair" in capsys.readouterr().err


def test_eval_student_stream_continues_a_sequence_and_restarts_on_the_next(tiny_student):
    """eval.py method student-stream: the pairs of one sequence are one stream (the same flows as a FlowStream fed
    the scans), a pair of another sequence starts a new one."""
    from fastflow3d.inference.eval_methods import StreamedStudentMethod

    data = SyntheticDataset(split="test", num_sequences=2, frames_per_sequence=4, beams=32, seed=3)
    pairs = [data[i] for i in range(len(data))]
    method = StreamedStudentMethod(tiny_student)
    flows = [method(pair, index) for index, pair in enumerate(pairs)]
    for sequence in (pairs[:3], pairs[3:]):
        assert len({pair.log_id for pair in sequence}) == 1
    first = pairs[0].log_id
    stream = FlowStream(Predictor.load(tiny_student))
    for start in (0, 3):
        stream.reset()
        stream.push(pairs[start].pc0)
        for k in range(start, start + 3):
            np.testing.assert_allclose(flows[k], stream.push(pairs[k].pc1).prediction.flow, atol=1e-6)
    assert pairs[3].log_id != first


def test_eval_student_stream_refine_is_the_refined_stream(tiny_student):
    """eval.py method student-stream+refine: the stream of a refining Predictor (what ``fastflow3d-infer MODEL DIR
    --refine`` runs), each pair's flow with its refinement mask."""
    from fastflow3d.inference.eval_methods import StreamedStudentMethod, refined_streamed_student_method
    from fastflow3d.inference.refine import RefineConfig

    pairs, _ = synthetic_drive(3, 4)
    method = refined_streamed_student_method(OmegaConf.create({"checkpoint": str(tiny_student)}))
    assert method.predictor.refine == RefineConfig()
    assert StreamedStudentMethod(tiny_student).predictor.refine is None
    stream = FlowStream(Predictor.load(tiny_student, refine=True))
    stream.push(pairs[0].pc0)
    for index, pair in enumerate(pairs):
        step = stream.push(pair.pc1)
        assert step.prediction.refined is not None
        np.testing.assert_allclose(method(pair, index), step.prediction.flow, atol=1e-6)


def test_infer_stream_gives_its_network_the_cores_but_one(tiny_student, moving, tmp_path, monkeypatch):
    """The stream overlaps each network with the next scan's steps: by default the network runs on one core fewer
    than the process may use (at least one), beside them; --threads overrides it, and a pair keeps every core."""
    from fastflow3d.inference import predictor
    from fastflow3d.inference.cli import main as infer_main

    asked = []
    load = predictor.Predictor.load.__func__

    def recording_load(cls, *args, **kwargs):
        asked.append(kwargs.get("threads"))
        return load(cls, *args, **kwargs)

    monkeypatch.setattr(predictor.Predictor, "load", classmethod(recording_load))
    _, scans = moving
    folder = tmp_path / "scans"
    folder.mkdir()
    for k, scan in enumerate(scans[:3]):
        np.save(folder / f"{k:06d}.npy", scan)
    for cores, expected in (({0, 1, 2, 3}, 3), ({0}, 1)):
        monkeypatch.setattr(os, "sched_getaffinity", lambda pid, cores=cores: cores, raising=False)
        assert overlap_threads() == expected
        assert infer_main([str(tiny_student), str(folder), "--out", str(tmp_path / f"out{expected}")]) == 0
        assert asked[-1] == expected
    assert infer_main([str(tiny_student), str(folder), "--out", str(tmp_path / "given"), "--threads", "2"]) == 0
    assert asked[-1] == 2
    pair = [str(folder / "000000.npy"), str(folder / "000001.npy"), "--out", str(tmp_path / "pair.npz")]
    assert infer_main([str(tiny_student), *pair]) == 0
    assert asked[-1] is None  # a pair: the engine's default, every usable core


def test_an_overlapped_stream_runs_its_own_steps_on_one_thread(tiny_student, moving, monkeypatch):
    """overlap=True: the stream's own steps (ground, odometry) run with numba and torch on one thread of the calling
    thread (their idle pool threads spun on the network's core), and the caller's settings come back after each push;
    the network and the refinement run in the worker thread, the refinement's numba kernels on every usable core there
    (the components of a pair spread over the cores the stream's own steps leave idle; the network keeps its engine's
    threads). A plain stream runs everything on the calling thread, as it is set."""
    import numba
    import torch

    from fastflow3d.inference import predictor as predictor_module

    seen = {"odometry": [], "refine": [], "network": []}
    where = {"refine": set(), "network": set()}
    predictor = Predictor.load(tiny_student, refine=True)
    refine_residual, network = predictor_module.refine_residual, predictor.run_network

    def threads(name, call):
        def recorded(*args, **kwargs):
            seen[name].append(settings())
            where.get(name, set()).add(threading.current_thread() is threading.main_thread())
            return call(*args, **kwargs)

        return recorded

    monkeypatch.setattr(predictor_module, "refine_residual", threads("refine", refine_residual))
    monkeypatch.setattr(predictor, "run_network", threads("network", network))

    def settings():
        return numba.get_num_threads(), torch.get_num_threads()

    before = settings()
    with ThreadPoolExecutor(1) as other:
        elsewhere = other.submit(settings).result()  # what a new thread has (the stream's worker is one)
    assert before[0] > 1 or numba.config.NUMBA_NUM_THREADS == 1  # a 2-core CI machine: 2
    _, scans = moving
    for overlap in (True, False):
        stream = FlowStream(predictor, overlap=overlap)
        monkeypatch.setattr(stream.odometry, "step", threads("odometry", stream.odometry.step))
        for scan in scans[:4]:
            stream.push(scan)
            assert settings() == before
        stream.flush()
        # KISS-ICP's registration (its own threads, out of threadpoolctl's reach) too
        assert stream.odometry._kiss.config.registration.max_num_threads == (1 if overlap else before[0])
        assert seen["odometry"] and set(seen["odometry"]) == {(1, 1) if overlap else before}, seen["odometry"]
        cores = min(available_cores(), numba.config.NUMBA_NUM_THREADS)
        assert set(seen["refine"]) == {(cores, elsewhere[1]) if overlap else before}, seen["refine"]
        assert where == {"refine": {not overlap}, "network": {not overlap}}, where
        seen = {name: [] for name in seen}
        where = {name: set() for name in where}
