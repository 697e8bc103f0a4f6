"""The evaluator: exact point-to-mesh queries, and known errors of fake runs on synthetic truth."""
import argparse
import json

import numpy as np
import pytest

from surfelwarp.data_tools import evaluate, meshes, synth
from surfelwarp.data_tools.geometry import TriangleMesh, closest_on_triangles
from surfelwarp.errors import InputError
from surfelwarp.geometry.se3 import invert, se3_exp
from surfelwarp.io.ply import vertex_table, write_ply

from conftest import shared_data



def test_closest_point_on_triangle_matches_brute_force():
    rng = np.random.default_rng(0)
    n = 60
    a, b, c = (rng.normal(size=(n, 3)) for _ in range(3))
    c[:10] = a[:10] + 0.01 * (b[:10] - a[:10]) + 1e-3 * rng.normal(size=(10, 3))   # slivers
    p = rng.normal(size=(n, 3)) * 2
    bary = closest_on_triangles(p, a, b, c)
    assert np.all(bary >= -1e-12) and np.allclose(bary.sum(1), 1)
    exact = np.linalg.norm(p - (bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c), axis=1)
    s, t = np.meshgrid(np.linspace(0, 1, 301), np.linspace(0, 1, 301))
    keep = s + t <= 1
    s, t = s[keep], t[keep]
    for i in range(n):
        q = a[i] + s[:, None] * (b[i] - a[i]) + t[:, None] * (c[i] - a[i])
        brute = np.linalg.norm(q - p[i], axis=1).min()
        step = max(np.linalg.norm(b[i] - a[i]), np.linalg.norm(c[i] - a[i])) / 300
        assert exact[i] <= brute + 1e-12 and exact[i] >= brute - step


def test_mesh_query_is_exact_with_mixed_triangle_sizes():
    ball, bf = meshes.sphere(0.05, 0.01)
    wall, wf = meshes.plane(1.0, 1.0, 0.25)
    v, f, _ = meshes.merge((ball + [0, 0, 0.3], bf), (wall + [0, 0, 0.5], wf))
    rng = np.random.default_rng(1)
    pts = np.vstack([rng.normal(scale=0.05, size=(200, 3)) + [0, 0, 0.3],
                     rng.uniform(-0.6, 0.6, size=(200, 3)) + [0, 0, 0.5],
                     rng.normal(scale=2.0, size=(50, 3))])
    mesh = TriangleMesh(v, f)
    fast = mesh.query(pts, k=4)
    assert len(mesh.search_points) > len(f)                 # the wall's big triangles are subdivided
    tri = v[f]
    rep = np.repeat(pts, len(f), axis=0)
    a, b, c = (np.tile(tri[:, i], (len(pts), 1)) for i in range(3))
    bary = closest_on_triangles(rep, a, b, c)
    brute = np.linalg.norm(rep - (bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c), axis=1)
    brute = brute.reshape(len(pts), len(f)).min(1)
    assert np.allclose(fast.distance, brute, atol=1e-12)
    # Without subdivision and with one candidate, only the exactness bound keeps it right:
    coarse = TriangleMesh(v, f, sample_radius_m=10.0)
    assert np.allclose(coarse.query(pts, k=1).distance, brute, atol=1e-12)
    first_guess = coarse._candidates(pts, 1)
    assert (first_guess[0] > brute + 1e-3).sum() >= 5 and not first_guess[4].all()
    assert np.allclose(fast.point, mesh.interpolate(v, fast.face, fast.bary))


def sample_surface(gt, frame_index, count, rng):
    """Random points on the GT mesh: (face, barycentric) pairs, area-weighted at that frame."""
    tri = gt.vertices[frame_index].astype(np.float64)[gt.faces]
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face = rng.choice(len(gt.faces), size=count, p=area / area.sum())
    r = rng.random((count, 2))
    flip = r.sum(1) > 1
    r[flip] = 1 - r[flip]
    return face, np.stack([1 - r.sum(1), r[:, 0], r[:, 1]], -1)


def at(gt, frame_index, face, bary, values=None):
    values = gt.vertices[frame_index].astype(np.float64) if values is None else values
    return np.einsum("ni,nij->nj", bary, values[gt.faces[face]])


def write_run(run, gt, saved, live_of, camera_to_world=None, reference=0):
    """A fake run: metrics.json for every GT frame, live PLYs for `saved` frames."""
    frames = []
    for i, frame in enumerate(gt.frames):
        pose = gt.camera_to_world[i] if camera_to_world is None else camera_to_world[i]
        frames.append({"frame": int(frame), "reference_frame": reference, "camera_to_world": pose.tolist(),
                       "seconds": {"total": 0.01}})
    run.mkdir(parents=True, exist_ok=True)
    (run / "metrics.json").write_text(json.dumps({"method": "fake", "frames": frames, "summary": {}}))
    for frame in saved:
        pos, nrm, ref = live_of(frame)
        write_ply(run / "live" / f"frame-{frame:06d}.ply", vertex_table(pos, nrm, ref))


@pytest.fixture(scope="module")
def sheet(tmp_path_factory):
    out = synth.generate("sheet", tmp_path_factory.mktemp("seq") / "sheet", frames=6, size=(160, 120), noise="none")
    return out, synth.load_groundtruth(out)


@pytest.mark.slow
def test_ground_truth_as_a_run_scores_perfectly_and_shifts_give_known_errors(sheet, tmp_path):
    seq, gt = sheet
    rng = np.random.default_rng(2)
    face, bary = sample_surface(gt, 0, 20000, rng)
    normals = [meshes.vertex_normals(gt.vertices[i], gt.faces) for i in range(len(gt.frames))]

    def live(shift_mm=0.0, lag=0):
        def of(frame):
            n = at(gt, frame, face, bary, normals[frame])
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            pos = at(gt, max(frame - lag, 0), face, bary) + 1e-3 * shift_mm * n
            return pos, n, at(gt, 0, face, bary)
        return of

    write_run(tmp_path / "exact", gt, [0, 3, 5], live())
    res = evaluate.evaluate(tmp_path / "exact", seq)
    avg = res["average"]
    assert avg["accuracy_median_mm"] < 1e-3 and avg["epe_mean_mm"] < 1e-3
    assert avg["normal_consistency"] > 0.9999
    assert avg["completeness_5mm_pct"] > 99 and avg["fscore_5mm_pct"] > 99 and avg["precision_5mm_pct"] == 100
    # Everything moves before a still camera: the pose carries the sheet's motion, no ATE.
    assert res["trajectory"]["ate_cm"] is None and "not a tracking error" in res["trajectory"]["note"]
    assert json.loads((tmp_path / "exact" / "eval.json").read_text())["average"] == avg

    write_run(tmp_path / "shifted", gt, [0, 3, 5], live(shift_mm=3.0))
    avg = evaluate.evaluate(tmp_path / "shifted", seq)["average"]
    assert abs(avg["accuracy_median_mm"] - 3.0) < 0.02 and abs(avg["accuracy_mean_mm"] - 3.0) < 0.05
    assert abs(avg["epe_mean_mm"] - 3.0) < 0.05 and abs(avg["epe_median_mm"] - 3.0) < 0.02
    assert avg["moving_points"] == 20000 and abs(avg["epe_moving_mean_mm"] - avg["epe_mean_mm"]) < 1e-9
    assert avg["precision_5mm_pct"] == 100 and avg["fscore_10mm_pct"] > 99
    assert avg["epe_under_1cm_pct"] == 100
    assert avg["far_2cm_pct"] == 0 and avg["depth_explained_1cm_pct"] > 99

    # A model that left the surface by 2.5 cm: every point far, no depth explained.
    write_run(tmp_path / "left", gt, [0, 3, 5], live(shift_mm=25.0))
    avg = evaluate.evaluate(tmp_path / "left", seq)["average"]
    assert avg["far_2cm_pct"] == 100 and avg["depth_explained_1cm_pct"] < 1

    # A tracker one frame behind: on the surface (accuracy ~0 only where the sheet is still)
    # but with the true motion of one frame as its end-point error.
    write_run(tmp_path / "lagging", gt, [3, 5], live(lag=1))
    res = evaluate.evaluate(tmp_path / "lagging", seq)
    for row in res["frames"]:
        f = row["frame"]
        motion = 1000 * np.linalg.norm(at(gt, f, face, bary) - at(gt, f - 1, face, bary), axis=1)
        assert abs(row["epe_mean_mm"] - motion.mean()) < 1e-3 and motion.mean() > 1.0
        assert abs(row["epe_under_1cm_pct"] - 100 * np.mean(motion < 10)) < 1e-9
        assert row["accuracy_median_mm"] > 0.1


def test_standing_still_scores_the_true_motion_since_the_first_frame(sheet, tmp_path):
    """What the observe method gets: exact geometry, no correspondence claimed (no EPE), and
    for scale the EPE that not tracking at all would have."""
    seq, gt = sheet
    face, bary = sample_surface(gt, 0, 20000, np.random.default_rng(3))

    def observed(frame):
        pos = at(gt, frame, face, bary)
        return pos, np.tile([0.0, 0.0, -1.0], (len(pos), 1)), pos

    run = tmp_path / "observe"
    write_run(run, gt, [0, 3, 5], observed)
    records = json.loads((run / "metrics.json").read_text())
    for f in records["frames"]:
        f["reference_frame"] = f["frame"]
    (run / "metrics.json").write_text(json.dumps(records))
    res = evaluate.evaluate(run, seq)
    rows = {r["frame"]: r for r in res["frames"]}
    assert rows[0]["zero_motion_epe_mm"] is None and all(r["epe_mean_mm"] is None for r in rows.values())
    for f in (3, 5):
        motion = 1000 * np.linalg.norm(at(gt, f, face, bary) - at(gt, 0, face, bary), axis=1).mean()
        assert rows[f]["zero_motion_epe_mm"] == pytest.approx(motion, rel=1e-3) and motion > 3
        assert rows[f]["accuracy_median_mm"] < 1e-3
    assert "EPE of standing still" in evaluate.format_table(res)


def test_moving_camera_and_trajectory_error(tmp_path):
    seq = synth.generate("orbit", tmp_path / "orbit", frames=5, size=(128, 96), noise="none")
    gt = synth.load_groundtruth(seq)
    rng = np.random.default_rng(3)
    face, bary = sample_surface(gt, 0, 8000, rng)
    # Each live point in its own frame's camera, its ref in frame 0's: EPE must still be 0.
    write_run(tmp_path / "run", gt, [0, 4], lambda f: (at(gt, f, face, bary), np.tile([0, 0, 1.0], (len(face), 1)),
                                                       at(gt, 0, face, bary)))
    res = evaluate.evaluate(tmp_path / "run", seq)
    assert res["average"]["epe_mean_mm"] < 1e-3 and res["average"]["accuracy_median_mm"] < 1e-3
    assert res["average"]["moving_points"] == 0 and res["average"]["epe_moving_mean_mm"] is None
    assert res["trajectory"]["ate_cm"] < 1e-9
    # Poses off by 1 cm along x after the first frame: ATE = sqrt(4/5) cm.
    bad = gt.camera_to_world.copy()
    bad[1:, 0, 3] += 0.01
    write_run(tmp_path / "run", gt, [0, 4], lambda f: (at(gt, f, face, bary), np.tile([0, 0, 1.0], (len(face), 1)),
                                                       at(gt, 0, face, bary)), camera_to_world=bad)
    traj = evaluate.evaluate(tmp_path / "run", seq)["trajectory"]
    assert abs(traj["ate_cm"] - np.sqrt(4 / 5)) < 1e-6 and traj["ate_aligned_cm"] < traj["ate_cm"]
    assert abs(traj["max_translation_error_mm"] - 10.0) < 1e-6
    assert traj["rotation_error_deg"] < 1e-6


def pose_only_run(run, poses, noise_m=0.0, rng=None):
    rel = [invert(poses[0]) @ p for p in poses]
    frames = []
    for i, p in enumerate(rel):
        p = p.copy()
        if noise_m:
            p[:3, 3] += rng.normal(scale=noise_m, size=3)
        frames.append({"frame": i, "reference_frame": 0, "camera_to_world": p.tolist()})
    run.mkdir(parents=True, exist_ok=True)
    (run / "metrics.json").write_text(json.dumps({"method": "fake", "frames": frames}))


def test_step_bias_is_the_lag_of_each_step_behind_the_true_one():
    """A trajectory whose every step is 98 % of the true one (an orbit of 20 frames, steps of
    ~16 mm): step bias -2 %; the true one: 0; a still camera: None (no step to measure)."""
    angles = np.linspace(0, 0.6, 20)
    truth = {f: se3_exp(np.array([0, a, 0, 0.5 * np.sin(a), 0, 0.5 * (1 - np.cos(a))])) for f, a in enumerate(angles)}
    centres = np.stack([truth[f][:3, 3] for f in range(20)])
    lagging = {}
    for f in range(20):
        T = truth[f].copy()
        T[:3, 3] = centres[0] + 0.98 * (centres[f] - centres[0])
        lagging[f] = T
    assert abs(evaluate.trajectory_errors(lagging, truth)["step_bias_pct"] + 2.0) < 1e-9
    assert abs(evaluate.trajectory_errors(truth, truth)["step_bias_pct"]) < 1e-12
    still = {f: np.eye(4) for f in range(5)}
    assert evaluate.trajectory_errors(still, still)["step_bias_pct"] is None
    assert evaluate.trajectory_errors({}, truth)["step_bias_pct"] is None


def test_seven_scenes_style_poses(tmp_path):
    seq = tmp_path / "seq"
    seq.mkdir()
    rng = np.random.default_rng(4)
    poses = [se3_exp(np.r_[0.3 * np.sin(0.1 * i + np.arange(3)), 0.05 * i, 1.0, -0.02 * i]) for i in range(30)]
    for i, p in enumerate(poses):
        np.savetxt(seq / f"frame-{i:06d}.pose.txt", p)
    pose_only_run(tmp_path / "run", poses)
    res = evaluate.evaluate(tmp_path / "run", seq)
    assert res["ground_truth"] == "poses" and res["frames"] == []
    assert res["trajectory"]["ate_cm"] < 1e-9 and res["trajectory"]["frames"] == 30
    pose_only_run(tmp_path / "noisy", poses, 0.01, np.random.default_rng(5))
    rel = [invert(poses[0]) @ p for p in poses]
    est = json.loads((tmp_path / "noisy" / "metrics.json").read_text())["frames"]
    # both are taken relative to the first frame; the noisy estimate's first pose is not identity
    e0 = np.asarray(est[0]["camera_to_world"])
    diffs = [(invert(e0) @ np.asarray(e["camera_to_world"]))[:3, 3] - r[:3, 3] for e, r in zip(est, rel)]
    expected = 100 * np.sqrt(np.mean(np.sum(np.array(diffs) ** 2, 1)))
    assert abs(evaluate.evaluate(tmp_path / "noisy", seq)["trajectory"]["ate_cm"] - expected) < 1e-9
    assert 1.0 < expected < 3.0


def test_real_seven_scenes_poses(tmp_path):
    data = shared_data("rigid-7scenes")
    poses = [np.loadtxt(data / f"frame-{i:06d}.pose.txt") for i in range(0, 200, 10)]
    rel = [np.linalg.solve(poses[0], p) for p in poses]
    frames = [{"frame": 10 * i, "reference_frame": 0, "camera_to_world": r.tolist()} for i, r in enumerate(rel)]
    (tmp_path / "metrics.json").write_text(json.dumps({"frames": frames}))
    traj = evaluate.evaluate(tmp_path, data)["trajectory"]
    assert traj["frames"] == 20 and traj["ate_cm"] < 1e-6


def test_cli_and_bad_input(sheet, tmp_path, capsys):
    seq, gt = sheet
    parser = argparse.ArgumentParser()
    evaluate.add_arguments(parser)
    with pytest.raises(InputError):
        evaluate.run(parser.parse_args([str(tmp_path / "nothing"), str(seq)]))
    (tmp_path / "run").mkdir()
    with pytest.raises(InputError):                       # no metrics.json
        evaluate.run(parser.parse_args([str(tmp_path / "run"), str(seq)]))
    write_run(tmp_path / "run", gt, [2], lambda f: (gt.vertices[f], np.zeros_like(gt.vertices[f]), gt.vertices[0]))
    with pytest.raises(InputError):                       # a folder without ground truth
        evaluate.run(parser.parse_args([str(tmp_path / "run"), str(tmp_path)]))
    assert evaluate.run(parser.parse_args([str(tmp_path / "run"), str(seq)])) == 0
    out = capsys.readouterr().out
    assert "no ATE" in out and out.count("\n") >= 4
    row = json.loads((tmp_path / "run" / "eval.json").read_text())["frames"][0]
    assert row["frame"] == 2 and row["normal_consistency"] is None and row["accuracy_median_mm"] < 1e-3


def test_moving_parts_epe_separates_the_tube_from_the_wall(tmp_path):
    seq = synth.generate("tube-wall", tmp_path / "tw", frames=4, size=(96, 72), noise="none")
    gt = synth.load_groundtruth(seq)
    rng = np.random.default_rng(6)
    on_tube = gt.moving[gt.faces].all(axis=1)
    face = np.concatenate([rng.choice(np.nonzero(on_tube)[0], 3000), rng.choice(np.nonzero(~on_tube)[0], 3000)])
    r = rng.random((6000, 2)) * 0.5
    bary = np.stack([1 - r.sum(1), r[:, 0], r[:, 1]], -1)
    write_run(tmp_path / "run", gt, [3], lambda f: (at(gt, f - 1, face, bary), np.tile([0, 0, 1.0], (6000, 1)),
                                                    at(gt, 0, face, bary)))
    row = evaluate.evaluate(tmp_path / "run", seq)["frames"][0]
    motion = 1000 * np.linalg.norm(at(gt, 3, face, bary) - at(gt, 2, face, bary), axis=1)
    assert motion[:3000].mean() > 2.0 and motion[3000:].max() == 0
    assert row["moving_points"] == 3000
    assert abs(row["epe_moving_mean_mm"] - motion[:3000].mean()) < 1e-3
    assert abs(row["epe_mean_mm"] - motion.mean()) < 1e-3


def test_scene_flow_epe_against_a_known_motion(tmp_path):
    """DeepDeform-style ground truth: a plane whose pixels move by a known flow."""
    import cv2

    seq = tmp_path / "seq"
    (seq / "depth").mkdir(parents=True)
    (seq / "scene_flow").mkdir()
    (seq / "mask").mkdir()
    w, h, fx = 64, 48, 60.0
    K = np.eye(4)
    K[0, 0] = K[1, 1] = fx
    K[0, 2], K[1, 2] = (w - 1) / 2, (h - 1) / 2
    np.savetxt(seq / "intrinsics.txt", K)
    for f in (0, 5):
        cv2.imwrite(str(seq / "depth" / f"{f:06d}.png"), np.full((h, w), 1000, np.uint16))
    flow = np.zeros((3, h, w), np.float32)
    flow[0], flow[2] = 0.02, -0.01                      # every pixel moves 2 cm right, 1 cm closer
    flow[:, :, :8] = -np.inf                            # unknown on the left
    (seq / "scene_flow" / "cloth_000000_000005.sflow").write_bytes(
        np.array([w, h, 3], "<u4").tobytes() + flow.astype("<f4").tobytes())
    mask = np.zeros((h, w), np.uint8)
    mask[:, : w // 2] = 255                              # the object is the left half
    cv2.imwrite(str(seq / "mask" / "000000_cloth.png"), mask)

    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    ref = np.stack([(u - K[0, 2]) / fx, (v - K[1, 2]) / fx, np.ones_like(u)], -1).reshape(-1, 3)
    error = np.array([0.003, 0.0, 0.004])                # the run misses the motion by 5 mm
    live = ref + [0.02, 0.0, -0.01] + error
    run = tmp_path / "run"
    frames = [{"frame": f, "reference_frame": 0, "camera_to_world": np.eye(4).tolist()} for f in (0, 5)]
    run.mkdir()
    (run / "metrics.json").write_text(json.dumps({"method": "fake", "frames": frames}))
    normals = np.tile([0.0, 0.0, -1.0], (len(ref), 1))
    write_ply(run / "live" / "frame-000005.ply", vertex_table(live, normals, ref))

    res = evaluate.evaluate(run, seq)
    row = res["frames"][0]
    assert res["ground_truth"] == "sceneflow" and row["frame"] == 5 and row["reference_frame"] == 0
    assert row["points"] == h * (w // 2 - 8)             # inside the mask, flow known
    assert abs(row["epe_mean_mm"] - 5.0) < 1e-3 and row["epe_under_1cm_pct"] == 100.0
    assert abs(row["zero_motion_epe_mm"] - 1000 * np.hypot(0.02, 0.01)) < 1e-3

    frames[1]["reference_frame"] = 5                     # a run that reinitialised cannot be scored
    (run / "metrics.json").write_text(json.dumps({"method": "fake", "frames": frames}))
    with pytest.raises(InputError, match="reference_frame"):
        evaluate.evaluate(run, seq)
