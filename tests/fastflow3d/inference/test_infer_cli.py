"""``fastflow3d-infer`` on raw scan files: with and without poses, the sensor height, one-line errors."""

import numpy as np
import pytest

from fastflow3d.inference.cli import main as infer_main
from fastflow3d.inference.predictor import Predictor

from helpers.exports import (
    TOLERANCE,
    lowered,
    write_poses,
    write_scan,
)

pytest.importorskip("onnxruntime")
pytest.importorskip("onnxscript")


def test_infer_cli_on_raw_files_with_and_without_poses(export_dir, pairs, expected, teacher_ego, tmp_path, capsys):
    pair, (flow, valid) = pairs[1], expected[1]
    poses = write_poses(tmp_path / "poses.txt", [pair.pose0, pair.pose1])
    for suffix0, suffix1, bev in ((".bin", ".npz", []), (".ply", ".pcd", ["--no-bev"])):
        scan0, scan1 = write_scan(tmp_path / f"a{suffix0}", pair.pc0), write_scan(tmp_path / f"b{suffix1}", pair.pc1)
        out = tmp_path / f"flow{suffix0}.npz"
        args = [str(export_dir), str(scan0), str(scan1), "--poses", str(poses), "--out", str(out), *bev]
        assert infer_main(args) == 0
        with np.load(out) as result:
            assert not result["ego_estimated"]
            np.testing.assert_allclose(result["ego1_from_ego0"], pair.ego1_from_ego0, atol=1e-9)
            assert np.abs(result["flow"] - flow).max() <= TOLERANCE
            assert np.array_equal(result["in_grid"], valid)
        assert out.with_suffix(".png").is_file() == (not bev)
    assert (tmp_path / "flow.bin.png").stat().st_size > 10_000
    scan0, scan1 = write_scan(tmp_path / "a.npy", pair.pc0), write_scan(tmp_path / "b.npy", pair.pc1)
    out = tmp_path / "estimated.npy"
    assert infer_main([str(export_dir / "fastflow3d.pt2"), str(scan0), str(scan1), "--out", str(out), "--no-bev"]) == 0
    got = np.load(out)
    assert got.shape == pair.pc0.shape and got.dtype == np.float32
    with_teacher_ego = Predictor.load(export_dir).predict(pair.pc0, pair.pc1, teacher_ego)
    assert np.abs(got - with_teacher_ego.flow).max() <= TOLERANCE
    assert "flow ->" in capsys.readouterr().out


def test_infer_cli_errors_are_one_line(export_dir, pairs, tmp_path, capsys):
    pair = pairs[2]
    good0, good1 = write_scan(tmp_path / "a.npy", pair.pc0), write_scan(tmp_path / "b.npy", pair.pc1)
    truncated = tmp_path / "cut.bin"
    truncated.write_bytes(np.ones(4 * 100 + 2, np.float32).tobytes())
    unnamed = tmp_path / "keys.npz"
    np.savez(unnamed, xyz=pair.pc0)
    three = write_poses(tmp_path / "three.txt", [np.eye(4)] * 3)
    sheared = tmp_path / "sheared.npy"
    np.save(sheared, np.diag([1.0, 2.0, 1.0, 1.0]))
    cases = [
        ([good0, tmp_path / "missing.npy"], "missing.npy: file not found"),
        ([truncated, good1], "cut.bin: size"),
        ([unnamed, good1], "keys.npz: no array named points or pc"),
        ([good0, tmp_path / "scan.xyz"], "scan.xyz: unsupported scan format"),
        ([good0, good1, "--poses", three], "three.txt: holds 3 transform(s), expected 2"),
        ([good0, good1, "--ego", sheared], "sheared.npy: transform 1 is not rigid"),
    ]
    for args, message in cases:
        assert infer_main([str(export_dir), *map(str, args), "--out", str(tmp_path / "x.npz")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("infer: ") and message in err, err
    assert infer_main([str(tmp_path), str(good0), str(good1)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not an export directory" in err
    assert not (tmp_path / "x.npz").exists()


def test_infer_cli_sensor_height(export_dir, pairs, expected, tmp_path, capsys):
    """--sensor-height 1.73 reads scans in a sensor frame; without it the CLI lifts them and says so in one line."""
    pair, (flow, _) = pairs[0], expected[0]
    pc0, pc1, ego = lowered(pair, 1.73)
    scan0, scan1 = write_scan(tmp_path / "a.npy", pc0), write_scan(tmp_path / "b.npy", pc1)
    transform = tmp_path / "ego.npy"
    np.save(transform, ego)
    out = tmp_path / "flow.npz"
    common = [str(export_dir), str(scan0), str(scan1), "--ego", str(transform), "--out", str(out), "--no-bev"]
    assert infer_main([*common, "--sensor-height", "1.73"]) == 0
    assert "warning: the ground" not in capsys.readouterr().err
    with np.load(out) as result:
        assert np.abs(result["flow"] - flow).max() <= 1e-3
    assert infer_main(common) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if "ground of pc0" in line]
    assert len(lines) == 1 and lines[0].startswith("infer: warning: the ground of pc0 lies at z = -1.")
    with pytest.raises(SystemExit):
        infer_main([*common, "--sensor-height", "tall"])


def test_a_tilde_in_any_path_option_is_the_home_folder(export_dir, pairs, tmp_path, monkeypatch):
    """``--out '~/x'`` (quoted: no shell expands it), the scans and ``--bev`` given with ``~``: the home folder, never
    a folder named ``~`` in the working directory."""
    home, work = tmp_path / "home", tmp_path / "work"
    home.mkdir()
    work.mkdir()
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.chdir(work)
    write_scan(home / "a.npy", pairs[1].pc0)
    write_scan(home / "b.npy", pairs[1].pc1)
    args = [str(export_dir), "~/a.npy", "~/b.npy", "--out", "~/flows/f.npz", "--bev", "~/flows/f.png"]
    assert infer_main(args) == 0
    assert (home / "flows" / "f.npz").is_file() and (home / "flows" / "f.png").is_file()
    assert not (work / "~").exists()
