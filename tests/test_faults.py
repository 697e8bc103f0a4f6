"""Faults cost nothing (issue 20): resume after a kill, no mixed runs, empty frames, gaps, bad
values and full disks end in one line; a seeded fuzz of damaged frames and config values."""
import contextlib
import errno
import io
import json
import pickle
import random
import signal
import subprocess
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from surfelwarp.cli import main
from surfelwarp.data_tools import synth
from surfelwarp.io.ply import read_ply

from conftest import two_colours, write_sequence
from test_cli import assert_clean_error, run_cli


def run_here(*args) -> tuple[int, str]:
    """`surfelwarp ARGS` in this process: (exit status, stderr). Anything but exit 0 or 2
    (an exception, a traceback) fails the test where it happens."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        quiet = ["--no-progress"] if args[0] in ("run", "compare", "bench") else []
        code = main([str(a) for a in args] + quiet)
    return code, err.getvalue()


def files_of(folder: Path) -> dict[Path, bytes]:
    return {p: p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def positions(path: Path) -> np.ndarray:
    table, _ = read_ply(path)
    return np.stack([table[k] for k in ("x", "y", "z", "ref_x", "ref_y", "ref_z")], 1)


def assert_same_run(a: Path, b: Path, tol_m: float = 1e-4):
    """The same live frames, model and poses, positions within tol_m (the contract's 0.1 mm)."""
    live_a = sorted(p.name for p in (a / "live").glob("frame-*.ply"))
    assert live_a == sorted(p.name for p in (b / "live").glob("frame-*.ply"))
    for name in live_a + ["../model.ply"]:
        pa, pb = positions(a / "live" / name), positions(b / "live" / name)
        assert pa.shape == pb.shape and np.abs(pa - pb).max() <= tol_m, name
    fa, fb = (json.loads((d / "metrics.json").read_text())["frames"] for d in (a, b))
    assert [f["frame"] for f in fa] == [f["frame"] for f in fb]
    assert all(np.abs(np.subtract(x["camera_to_world"], y["camera_to_world"])).max() <= tol_m for x, y in zip(fa, fb))


def consistent(out: Path) -> list[int]:
    """metrics.json's frames, after checking that live/ holds only frames it lists (readable),
    but for at most one newer one: the live PLY is written before the metrics that list it, so
    a kill between the two leaves it ahead (--resume writes it again)."""
    metrics = json.loads((out / "metrics.json").read_text())
    frames = [f["frame"] for f in metrics["frames"]]
    live = sorted(int(p.stem[6:]) for p in (out / "live").glob("frame-*.ply"))
    listed = [i for i in live if i <= frames[-1]]
    assert set(listed) <= set(frames) and len(live) - len(listed) <= 1 and listed and listed[0] == frames[0]
    for i in live:
        assert len(read_ply(out / "live" / f"frame-{i:06d}.ply")[0]) > 0
    return frames


@pytest.fixture(scope="module")
def touch(tmp_path_factory) -> Path:
    """A deforming, coloured synthetic scene: 24 frames, 320x240."""
    return synth.generate("touch", tmp_path_factory.mktemp("touch") / "seq", frames=24, size=(320, 240))


@pytest.fixture(scope="module")
def touch_run(touch, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("full") / "out"
    assert run_here("run", touch, "--out", out, "--save-every", 5)[0] == 0
    return out


# ---------------------------------------------------------------- resume

@pytest.mark.slow
def test_kill_then_resume_gives_the_uninterrupted_run(touch, touch_run, tmp_path):
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "surfelwarp", "run", str(touch), "--out", str(out),
                             "--save-every", "5", "--no-progress"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.time() + 120
    while not (out / "live" / "frame-000010.ply").exists():
        assert proc.poll() is None and time.time() < deadline, proc.stderr.read()
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (out / "model.ply").exists(), "killed before the end"
    assert consistent(out)[-1] >= 5
    code, err = run_here("run", touch, "--out", out, "--save-every", 5, "--resume")
    assert code == 0, err
    assert_same_run(touch_run, out)


def test_resume_past_max_frames_and_refusals(touch, touch_run, tmp_path):
    out = tmp_path / "out"
    assert run_here("run", touch, "--out", out, "--save-every", 5, "--max-frames", 12)[0] == 0
    assert json.loads((out / "metrics.json").read_text())["summary"]["frames"] == 12
    # another parameter: refused in one line, nothing touched
    before = files_of(out)
    code, err = run_here("run", touch, "--out", out, "--save-every", 5, "--resume", "--camera", "static")
    assert_clean_error(code, err, "checkpoint.pkl", "belongs to another run", "tracking.camera")
    code, err = run_here("run", touch, "--out", out, "--save-every", 4, "--resume")
    assert_clean_error(code, err, "save_every")
    assert files_of(out) == before
    # a checkpoint of another format (a method whose state had other fields): refused, untouched
    state = pickle.loads((out / "checkpoint.pkl").read_bytes())
    old = tmp_path / "old"
    old.mkdir()
    (old / "checkpoint.pkl").write_bytes(pickle.dumps(replace(state, format=state.format - 1)))
    code, err = run_here("run", touch, "--out", old, "--save-every", 5, "--resume")
    assert_clean_error(code, err, "checkpoint.pkl", "another version of surfelwarp")
    # more frames: goes on to the end, as if run whole
    assert run_here("run", touch, "--out", out, "--save-every", 5, "--resume")[0] == 0
    assert_same_run(touch_run, out)
    # nothing to resume from
    code, err = run_here("run", touch, "--out", tmp_path / "empty", "--resume")
    assert_clean_error(code, err, "nothing to resume")
    (out / "checkpoint.pkl").write_bytes(b"\x80\x04garbage")
    code, err = run_here("run", touch, "--out", out, "--resume")
    assert_clean_error(code, err, "checkpoint cannot be read")


def test_dynamicfusion_resumes_too(tmp_path):
    seq = write_sequence(tmp_path / "seq", frames=range(6), color=two_colours)
    config = tmp_path / "coarse.json"
    config.write_text('{"tsdf": {"voxel_size_m": 0.02, "truncation_m": 0.06}}')
    args = ("run", seq, "--method", "dynamicfusion", "--config", config, "--save-every", 2)
    assert run_here(*args, "--out", tmp_path / "full")[0] == 0
    assert run_here(*args, "--out", tmp_path / "part", "--max-frames", 3)[0] == 0
    assert run_here(*args, "--out", tmp_path / "part", "--resume")[0] == 0
    assert_same_run(tmp_path / "full", tmp_path / "part")


# ---------------------------------------------------------------- no mixed runs

def test_rerun_failing_part_way_leaves_only_its_own_frames(tmp_path):
    seq = write_sequence(tmp_path / "seq", frames=range(8))
    out = tmp_path / "out"
    assert run_here("run", seq, "--out", out, "--save-every", 1)[0] == 0
    frame = seq / "frame-000004.depth.png"
    frame.write_bytes(frame.read_bytes()[:40] + b"\0" * 200)     # header intact, pixels damaged
    code, err = run_here("run", seq, "--out", out, "--save-every", 1)
    assert_clean_error(code, err, "frame-000004.depth.png")
    assert consistent(out) == [0, 1, 2, 3]
    assert not (out / "model.ply").exists() and not (out / "surfels.png").exists()
    assert sorted(p.name for p in (out / "live").iterdir()) == [f"frame-{i:06d}.ply" for i in range(4)]


def test_out_equal_to_or_inside_the_input_is_refused(tmp_path):
    seq = write_sequence(tmp_path / "seq", frames=range(2))
    before = files_of(seq)
    for out in (seq, seq / "out", seq / "." / "a" / ".."):
        code, err = run_here("run", seq, "--out", out)
        assert_clean_error(code, err, "output folder is the input folder")
    assert files_of(seq) == before


# ---------------------------------------------------------------- empty frames, gaps

@pytest.mark.parametrize("method", ["surfelwarp", "dynamicfusion", "observe"])
def test_empty_frames_are_skipped_then_held(tmp_path, method):
    seq = write_sequence(tmp_path / "seq", frames=range(7))
    empty = np.zeros((48, 64), np.uint16)
    for i in (0, 1, 4):
        cv2.imwrite(str(seq / f"frame-{i:06d}.depth.png"), empty)
    config = tmp_path / "coarse.json"
    config.write_text('{"tsdf": {"voxel_size_m": 0.02, "truncation_m": 0.06}}')
    extra = ("--config", config) if method == "dynamicfusion" else ()
    code, err = run_here("run", seq, "--out", tmp_path / "out", "--method", method, "--save-every", 3, *extra)
    assert code == 0, err
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert [f["frame"] for f in metrics["frames"]] == [2, 3, 4, 5, 6]
    assert metrics["summary"]["skipped_frames"] == [0, 1] and metrics["summary"]["untracked_frames"] == [4]
    held, before = metrics["frames"][2], metrics["frames"][1]
    assert held["tracked"] is False and held["camera_to_world"] == before["camera_to_world"]
    assert held.get("surfels") == before.get("surfels")
    # the first processed frame is always saved (the live model of its reference)
    assert sorted(p.name for p in (tmp_path / "out" / "live").iterdir()) == \
        ["frame-000002.ply", "frame-000003.ply", "frame-000006.ply"]


def test_no_frame_to_start_from_is_one_line(tmp_path):
    seq = write_sequence(tmp_path / "seq", frames=range(3))
    for i in range(3):
        cv2.imwrite(str(seq / f"frame-{i:06d}.depth.png"), np.zeros((48, 64), np.uint16))
    code, err = run_here("run", seq, "--out", tmp_path / "out")
    assert_clean_error(code, err, "no frame has enough valid depth", "3 skipped")
    assert not (tmp_path / "out").exists()


def test_gaps_in_frame_numbers_are_named_once(tmp_path):
    seq = write_sequence(tmp_path / "seq", frames=[0, 1, 3, 7, 8])
    code, _, err = run_cli("run", seq, "--out", tmp_path / "out", "--method", "observe")
    assert code == 0 and err.count("missing") == 1 and "4 frame number(s) missing" in err and ": 2, 4-6" in err, err
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["summary"]["missing_frames"] == [2, 4, 5, 6]
    assert [f["frame"] for f in metrics["frames"]] == [0, 1, 3, 7, 8]


# ---------------------------------------------------------------- bad values, full disk

@pytest.mark.parametrize("flags, fragment", [
    (("--intrinsics", "nan,nan,1,1"), "finite"),
    (("--intrinsics", "570,570,inf,240"), "finite"),
    (("--intrinsics", "60,60,500,24"), "principal point (500, 24) lies outside the 64x48 image"),
    (("--voxel-size", "nan"), "--voxel-size"),
    (("--voxel-size", "inf"), "--voxel-size"),
])
def test_flags_out_of_range(tmp_path, flags, fragment):
    seq = write_sequence(tmp_path / "seq", frames=range(2))
    command = "compare" if flags[0] == "--voxel-size" else "run"
    code, err = run_here(command, seq, "--out", tmp_path / "out", *flags)
    assert_clean_error(code, err, fragment)
    assert not (tmp_path / "out").exists()


def test_principal_point_outside_the_image_in_a_file(tmp_path):
    seq = write_sequence(tmp_path / "seq", frames=range(2))
    (seq / "depthIntrinsics.txt").write_text("60 0 32\n0 60 -5\n0 0 1\n")
    code, err = run_here("run", seq, "--out", tmp_path / "out")
    assert_clean_error(code, err, "depthIntrinsics.txt", "principal point (32, -5)")


@pytest.mark.slow
@pytest.mark.parametrize("fail_at", [1, 4, 9])
def test_full_disk_ends_in_one_line_and_the_run_resumes(tmp_path, monkeypatch, fail_at):
    """The fail_at-th file written fails as on a full disk: one line, exit 2, no temporary
    files, live/ and metrics.json consistent; with space again, --resume ends as a whole run."""
    seq = write_sequence(tmp_path / "seq", frames=range(8))
    assert run_here("run", seq, "--out", tmp_path / "whole", "--save-every", 2)[0] == 0
    out = tmp_path / "out"
    import surfelwarp.io.ply as ply
    real, calls = ply.os.replace, []

    def replace(src, dst):
        calls.append(dst)
        if len(calls) >= fail_at:
            raise OSError(errno.ENOSPC, "No space left on device")
        real(src, dst)

    monkeypatch.setattr(ply.os, "replace", replace)
    code, err = run_here("run", seq, "--out", out, "--save-every", 2)
    assert_clean_error(code, err, "cannot write (No space left on device)")
    assert not list(out.rglob(".*tmp*")), "temporary files are removed"
    monkeypatch.undo()
    if (out / "checkpoint.pkl").exists():
        if (out / "metrics.json").exists():     # (the fault may have hit the first metrics)
            consistent(out)
        assert run_here("run", seq, "--out", out, "--save-every", 2, "--resume")[0] == 0
    else:                                    # failed before its first checkpoint: start again
        assert fail_at <= 2 and not (out / "metrics.json").exists()
        assert run_here("run", seq, "--out", out, "--save-every", 2)[0] == 0
    assert_same_run(tmp_path / "whole", out)


# ---------------------------------------------------------------- fuzz

CONFIG_KEYS = [("warp_field", "node_radius_m"), ("warp_field", "sigma_m"), ("warp_field", "k_skin"),
               ("fusion", "window"), ("fusion", "normal_threshold"), ("fusion", "distance_threshold_m"),
               ("index_map_supersample",), ("tracking", "nonrigid", "lambda_reg"),
               ("tracking", "nonrigid", "max_iterations"), ("tracking", "rigid", "pyramid_levels"),
               ("tracking", "rigid", "distance_gate_m"), ("tracking", "hierarchy", "beta"),
               ("tracking", "features", "ratio"), ("tracking", "features", "flow_stride_px"),
               ("tracking", "anchor", "release_sigmas"), ("reinit", "every_frames"), ("append", "strain_step_m"),
               ("tracking", "nonrigid", "silhouette", "hole_px"), ("tracking", "camera"), ("recent_draw",),
               ("tracking", "nonrigid", "terms"), ("no_such_key",)]
VALUES = [0, 0.0, -1, 1e-9, 0.5, 1, 2, 3, 7, 100, 1e9, "nan", "inf", "text", True, [1, 2, 3], [], {}, None]
FLAGS = [("--depth-scale", ["0", "-5", "nan", "1e-30", "5000", "x"]), ("--clip-near", ["-1", "nan", "0", "0.5", "9"]),
         ("--clip-far", ["0", "inf", "nan", "0.3", "x"]), ("--intrinsics", ["1,2,3", "60,60,32,24", "0,60,32,24",
                                                                            "60,nan,32,24", "a,b,c,d"]),
         ("--start", ["-3", "1", "99", "x"]), ("--max-frames", ["0", "1", "-2", "x"]), ("--save-every", ["0", "1"])]


def damage(path: Path, rng: random.Random) -> None:
    data = bytearray(path.read_bytes())
    kind = rng.choice(["flip", "truncate", "zero", "empty"])
    if kind == "flip":
        for _ in range(rng.randint(1, 8)):
            data[rng.randrange(len(data))] = rng.randrange(256)
    elif kind == "truncate":
        data = data[:rng.randrange(len(data))]
    elif kind == "zero":
        start = rng.randrange(len(data))
        data[start:start + rng.randint(1, 64)] = bytes(min(64, len(data) - start))
    else:
        data = bytearray()
    path.write_bytes(bytes(data))


@pytest.mark.slow
def test_fuzz_every_case_is_exit_0_or_one_line(tmp_path, capfd):
    """Seeded: damaged depth, colour and intrinsics files, config values of every type and
    range, flags; every case ends with exit 0, or exit 2 and one line (read at the file
    descriptor, where libpng would print its own complaints), and writes only in OUT."""
    rng = random.Random(20)
    pristine = write_sequence(tmp_path / "pristine", frames=range(3), color=two_colours)
    outcomes = {0: 0, 2: 0}
    started = time.time()
    for case in range(300):
        work = tmp_path / f"case{case}"
        seq = work / "seq"
        seq.mkdir(parents=True)
        for p in pristine.iterdir():
            (seq / p.name).write_bytes(p.read_bytes())
        args = ["run", seq, "--out", work / "out", "--method", rng.choice(["surfelwarp", "observe", "surfelwarp"])]
        what = rng.choice(["frame", "config", "flag"])
        if what == "frame":
            damage(rng.choice(sorted(seq.iterdir())), rng)
        elif what == "config":
            table, value = {}, rng.choice(VALUES)
            for _ in range(rng.randint(1, 2)):
                *parents, leaf = rng.choice(CONFIG_KEYS)
                node = table
                for name in parents:
                    node = node.setdefault(name, {}) if isinstance(node.get(name, {}), dict) else {}
                node[leaf] = float(value) if value in ("nan", "inf") else value
            (work / "config.json").write_text(json.dumps(table))
            args += ["--config", work / "config.json", "--method", "surfelwarp"]
        else:
            flag, choices = rng.choice(FLAGS)
            args += [flag, rng.choice(choices)]
        before = files_of(seq)
        capfd.readouterr()
        try:
            with warnings.catch_warnings():     # a warning would be a second line on stderr
                warnings.simplefilter("error")
                code = main([str(a) for a in args] + ["--no-progress"])
        except SystemExit as exc:        # argparse's own usage errors: exit 2 and one line
            code, err = exc.code, capfd.readouterr().err
            assert code == 2 and len(err.strip().splitlines()) == 1 and "error:" in err, (case, args, err)
        else:
            err = capfd.readouterr().err
        assert code in (0, 2), (case, args, err)
        if code == 2 and err:
            assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, (case, args, err)
        outcomes[code] += 1
        assert files_of(seq) == before, (case, args)
        assert sorted(p.name for p in work.iterdir()) in (["seq"], ["out", "seq"], ["config.json", "seq"],
                                                        ["config.json", "out", "seq"]), (case, args)
    print(f"fuzz outcomes by exit status: {outcomes}")
    assert outcomes[0] >= 30 and outcomes[2] >= 100, outcomes
    assert time.time() - started < 120


@pytest.mark.slow
def test_fuzz_mesh_and_view_of_damaged_outputs(touch_run, tmp_path, capfd):
    """Damaged model, live PLYs and metrics: `mesh` and `view` end with exit 0, or 2 and one line."""
    rng = random.Random(21)
    names = ["model.ply", "live/frame-000010.ply", "metrics.json"]
    for case in range(60):
        work = tmp_path / f"case{case}"
        (work / "live").mkdir(parents=True)
        for name in names + ["live/frame-000005.ply"]:
            (work / name).write_bytes((touch_run / name).read_bytes())
        damage(work / rng.choice(names), rng)
        for argv in (["mesh", work], ["mesh", work, "--frame", "10"], ["view", work]):
            capfd.readouterr()
            with warnings.catch_warnings():     # a warning would be a second line on stderr
                warnings.simplefilter("error")
                code = main([str(a) for a in argv])
            err = capfd.readouterr().err
            assert code in (0, 2) and (code == 0 or len(err.strip().splitlines()) == 1), (case, argv, err)
