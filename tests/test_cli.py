import json
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest

from surfelwarp.io.ply import read_ply

from conftest import SPHERE_RGB, WALL_RGB, two_colours, write_sequence


def run_cli(*args):
    proc = subprocess.run([sys.executable, "-m", "surfelwarp", *map(str, args)], capture_output=True, text=True)
    return proc.returncode, proc.stdout, proc.stderr


def test_observe_run_writes_the_contract(tmp_path):
    seq = write_sequence(tmp_path / "seq", frames=range(5))
    out = tmp_path / "out"
    code, stdout, stderr = run_cli("run", seq, "--out", out, "--method", "observe", "--save-every", 2)
    assert code == 0, stderr
    assert str(out) in stdout
    assert sorted(p.name for p in (out / "live").iterdir()) == [f"frame-{i:06d}.ply" for i in (0, 2, 4)]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["method"] == "observe" and metrics["summary"]["frames"] == 5
    assert metrics["summary"]["median_frame_seconds"] > 0 and metrics["summary"]["peak_rss_mb"] > 10
    for i, frame in enumerate(metrics["frames"]):
        assert frame["frame"] == i and frame["reference_frame"] == i
        assert np.allclose(frame["camera_to_world"], np.eye(4))
        assert {"preprocess", "total"} <= frame["seconds"].keys()
        # total is the whole frame: its stages, and on a saved frame its writing, add up within it
        parts = {k: v for k, v in frame["seconds"].items() if k != "total"}
        assert sum(parts.values()) <= frame["seconds"]["total"] + 1e-5
        assert ({"write", "render"} <= parts.keys()) == (i % 2 == 0)
        assert frame["surfels"] > 1000
        assert {"nodes", "gauss_newton_iterations", "energy", "reinitialized"} <= frame.keys()
    assert metrics["config"]["preprocess"]["clip_far_m"] == 3.0
    vertices, faces = read_ply(out / "live" / "frame-000004.ply")
    assert vertices.dtype.names == ("x", "y", "z", "nx", "ny", "nz", "ref_x", "ref_y", "ref_z",
                                    "radius", "confidence", "id")
    assert all(vertices.dtype[n] == np.dtype("<f4") for n in vertices.dtype.names[:-1])
    assert vertices.dtype["id"] == np.dtype("<u4") and faces is None
    assert len(vertices) == metrics["frames"][4]["surfels"]
    # The sphere's front point is 0.8 m away; the wall is at 1.5 m.
    assert vertices["z"].min() == pytest.approx(0.8, abs=0.01) and vertices["z"].max() == pytest.approx(1.5, abs=0.01)
    model, _ = read_ply(out / "model.ply")
    assert len(model) == len(vertices)
    # Ids are never reused across frames.
    first, _ = read_ply(out / "live" / "frame-000000.ply")
    assert set(first["id"]).isdisjoint(set(vertices["id"]))


def assert_clean_error(code, stderr, *fragments):
    assert code == 2
    assert "Traceback" not in stderr
    assert len(stderr.strip().splitlines()) == 1, stderr
    for fragment in fragments:
        assert fragment in stderr, stderr


def test_folder_matching_no_layout(tmp_path):
    (tmp_path / "empty").mkdir()
    code, _, err = run_cli("run", tmp_path / "empty", "--out", tmp_path / "out")
    assert_clean_error(code, err, str(tmp_path / "empty"), "no known sequence layout")
    code, _, err = run_cli("run", tmp_path / "missing", "--out", tmp_path / "out")
    assert_clean_error(code, err, "does not exist")


def test_intrinsics_that_do_not_parse(tmp_path):
    seq = write_sequence(tmp_path / "seq")
    (seq / "depthIntrinsics.txt").write_text("525 0 320\n0 abc 240\n")
    code, _, err = run_cli("run", seq, "--out", tmp_path / "out")
    assert_clean_error(code, err, "depthIntrinsics.txt", "does not parse")
    (seq / "depthIntrinsics.txt").write_text("525 0 320 0 525\n")
    code, _, err = run_cli("run", seq, "--out", tmp_path / "out")
    assert_clean_error(code, err, "depthIntrinsics.txt", "found 5")


@pytest.mark.parametrize("bad", ["8bit", "rgb16", "size", "missing", "not_png"])
def test_bad_frames_are_named(tmp_path, bad):
    seq = write_sequence(tmp_path / "seq", frames=range(4))
    frame = seq / "frame-000002.depth.png"
    frame.unlink()
    if bad == "8bit":
        cv2.imwrite(str(frame), np.zeros((48, 64), np.uint8))
    elif bad == "rgb16":
        cv2.imwrite(str(frame), np.zeros((48, 64, 3), np.uint16))
    elif bad == "size":
        cv2.imwrite(str(frame), np.zeros((40, 64), np.uint16))
    elif bad == "missing":
        os.symlink(seq / "nowhere.png", frame)
    else:
        frame.write_text("hello")
    out = tmp_path / "out"
    code, _, err = run_cli("run", seq, "--out", out)
    expected = {"8bit": "16-bit single-channel", "rgb16": "16-bit single-channel", "size": "64x40",
                "missing": "cannot read frame", "not_png": "not a PNG"}[bad]
    assert_clean_error(code, err, "frame-000002.depth.png", expected)
    assert not out.exists(), "frames are checked before anything is written"


def test_damaged_frame_mid_run_keeps_earlier_outputs(tmp_path):
    seq = write_sequence(tmp_path / "seq", frames=range(4))
    frame = seq / "frame-000002.depth.png"
    data = frame.read_bytes()
    frame.write_bytes(data[:40] + b"\0" * (len(data) - 40))   # header intact, pixels damaged
    out = tmp_path / "out"
    code, _, err = run_cli("run", seq, "--out", out, "--save-every", 1)
    assert_clean_error(code, err, "frame-000002.depth.png", "cannot decode")
    metrics = json.loads((out / "metrics.json").read_text())
    assert [f["frame"] for f in metrics["frames"]] == [0, 1]
    assert "frame-000002" in metrics["error"]
    assert len(read_ply(out / "live" / "frame-000001.ply")[0]) > 1000
    assert not list((out / "live").glob(".*tmp*"))


def test_failed_run_does_not_touch_earlier_outputs(tmp_path):
    seq = write_sequence(tmp_path / "seq", frames=range(2))
    out = tmp_path / "out"
    assert run_cli("run", seq, "--out", out)[0] == 0
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    (seq / "depthIntrinsics.txt").write_text("garbage")
    code, _, err = run_cli("run", seq, "--out", out)
    assert code == 2
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_bad_flags(tmp_path):
    seq = write_sequence(tmp_path / "seq")
    code, _, err = run_cli("run", seq, "--out", tmp_path / "o", "--clip-near", "2", "--clip-far", "1")
    assert_clean_error(code, err, "--clip-near")
    for scale in ("0", "inf"):
        code, _, err = run_cli("run", seq, "--out", tmp_path / "o", "--depth-scale", scale)
        assert_clean_error(code, err, "--depth-scale")
    code, _, err = run_cli("run", seq, "--out", tmp_path / "o", "--clip-far", "inf")
    assert_clean_error(code, err, "--clip-far")
    # argparse's own errors are one line too, not after a usage block
    code, _, err = run_cli("run", seq, "--out", tmp_path / "o", "--max-frames", "0")
    assert_clean_error(code, err, "--max-frames")
    code, _, err = run_cli("run", seq, "--out", tmp_path / "o", "--camera", "sideways")
    assert_clean_error(code, err, "--camera", "sideways")
    code, _, err = run_cli("run", seq, "--out", tmp_path / "o", "--start", "99")
    assert_clean_error(code, err, "no depth frames")


def test_rerun_into_the_same_folder_leaves_only_its_own_frames(tmp_path):
    seq = write_sequence(tmp_path / "seq", frames=range(6))
    out = tmp_path / "out"
    assert run_cli("run", seq, "--out", out, "--method", "observe", "--save-every", 1)[0] == 0
    (out / "live" / "notes.txt").write_text("mine")
    assert run_cli("mesh", out, "--frame", 4)[0] == 0 and run_cli("view", out)[0] == 0
    assert (out / "mesh" / "frame-000004.ply").is_file() and (out / "view.html").is_file()
    assert run_cli("run", seq, "--out", out, "--method", "observe", "--max-frames", 3)[0] == 0
    assert sorted(p.name for p in (out / "live").iterdir()) == ["frame-000000.ply", "frame-000002.ply", "notes.txt"]
    # what `mesh` and `view` made of the earlier run went with it
    assert not (out / "mesh" / "frame-000004.ply").exists() and not (out / "view.html").exists()
    metrics = json.loads((out / "metrics.json").read_text())
    assert [f["frame"] for f in metrics["frames"]] == [0, 1, 2]


def test_colour_frame_damaged_mid_run_is_one_clear_error(tmp_path):
    seq = write_sequence(tmp_path / "seq", frames=range(4), color=two_colours)
    frame = seq / "frame-000002.color.png"
    data = frame.read_bytes()
    frame.write_bytes(data[:40] + b"\0" * (len(data) - 40))   # header intact, pixels damaged
    out = tmp_path / "out"
    code, _, err = run_cli("run", seq, "--out", out, "--method", "observe", "--save-every", 1)
    assert_clean_error(code, err, "frame-000002.color.png", "cannot decode colour frame")
    metrics = json.loads((out / "metrics.json").read_text())
    assert [f["frame"] for f in metrics["frames"]] == [0, 1] and "frame-000002.color.png" in metrics["error"]


def test_unreadable_colour_file_is_named_before_anything_is_written(tmp_path):
    seq = write_sequence(tmp_path / "seq", frames=range(3), color=two_colours)
    (seq / "frame-000001.color.png").write_text("hello")
    out = tmp_path / "out"
    code, _, err = run_cli("run", seq, "--out", out)
    assert_clean_error(code, err, "frame-000001.color.png", "not a PNG")
    assert not out.exists()


@pytest.mark.parametrize("method", ["surfelwarp", "dynamicfusion"])
def test_coloured_run_goes_on_past_a_frame_without_colour(tmp_path, method):
    seq = write_sequence(tmp_path / "seq", frames=range(3), color=two_colours)
    (seq / "frame-000001.color.png").unlink()
    config = tmp_path / "coarse.json"      # 2 cm voxels: the 64x48 frames' pixels are 2.5 cm on the wall
    config.write_text('{"tsdf": {"voxel_size_m": 0.02, "truncation_m": 0.06}}')
    out = tmp_path / "out"
    code, _, err = run_cli("run", seq, "--out", out, "--method", method, "--no-progress",
                           *(["--config", config] if method == "dynamicfusion" else []))
    assert code == 0, err
    assert err.count("surfelwarp: note:") == 1 and "1 of 3 frames have no colour frame" in err, err
    assert json.loads((out / "metrics.json").read_text())["config"]["input"]["color"] is True
    for path in (out / "live" / "frame-000002.ply", out / "model.ply"):
        table, _ = read_ply(path)
        assert table.dtype.names[-3:] == ("red", "green", "blue")
        rgb = np.stack([table["red"], table["green"], table["blue"]], 1).astype(int)
        for part, painted in ((table["z"] < 1.35, SPHERE_RGB), (table["z"] > 1.45, WALL_RGB)):
            assert part.sum() > 300 and np.mean(np.abs(rgb[part] - painted).max(1) <= 2) > 0.99
